"""What exists, listed from where it is declared: ``gonio models`` (the model catalogue),
``gonio plans`` (the plan presets, the simulator's error presets), the example samples shipped
with the command line (``gonio/cli/samples/*.toml``), and the units ``gonio settings show``
prints beside each value.

Nothing here is a hand-kept list: a new model file in gonio/models/catalogue, a new preset
TOML in gonio/bench/plan/presets or a new sample TOML in gonio/cli/samples shows up by itself.
Every line fits 80 columns.
"""

from __future__ import annotations

import re
import shutil
import textwrap
import tomllib
from importlib import resources
from pathlib import Path

__all__ = ["models_lines", "plans_lines", "example_samples", "sample_path", "settings_lines_with_units",
           "unit_of", "text_width"]

#: the widest any listing is, whatever the terminal
MAX_WIDTH = 80


def text_width() -> int:
    """The terminal's width up to 80 columns (80 in a pipe)."""
    return max(40, min(shutil.get_terminal_size((MAX_WIDTH, 24)).columns, MAX_WIDTH))


def _entry(name: str, middle: str, text: str, name_w: int, middle_w: int, width: int) -> list[str]:
    """``  name  middle  text`` with the text wrapped under itself."""
    head = f"  {name:<{name_w}}  {middle:>{middle_w}}  " if middle_w else f"  {name:<{name_w}}  "
    if len(head) > width // 2:          # a long name: the text on the lines below
        return [head.rstrip()] + textwrap.wrap(text, width, initial_indent=" " * 6, subsequent_indent=" " * 6,
                                               break_on_hyphens=False)
    return textwrap.wrap(text, width, initial_indent=head, subsequent_indent=" " * len(head),
                         break_on_hyphens=False) or [head.rstrip()]


def _plain(doc: str) -> str:
    """A docstring's first sentence as plain text (reST markup and ``(see the module)`` gone)."""
    para = " ".join((doc or "").strip().split("\n\n")[0].split())
    para = re.sub(r":\w+:`~([^`]+)`", lambda m: m.group(1).split(".")[-1], para)
    para = re.sub(r":\w+:`([^`]+)`", r"\1", para).replace("``", "").replace("`", "")
    para = re.sub(r"\s*\(see [^)]*\)", "", para)
    sentence = re.split(r"(?<=\.)\s", para, maxsplit=1)[0]
    return sentence.rstrip(".;:,")


# --------------------------------------------------------------------------- models
def models_lines(width: int | None = None) -> list[str]:
    """``gonio models``: every registered model, a line (wrapped) each: name, fitted numbers,
    what it is, its options; ``*`` marks the candidates of ``--model auto``."""
    import gonio.models as gm

    width = width or text_width()
    rows = []
    for name in gm.names():
        model = gm.get(name)
        cls = type(model)
        k = sum(3 if p.per_channel else 1 for p in model.parameters)
        opts = "; ".join(f"{key}={'|'.join(str(v).lower() for v in values)}"
                         for key, values in getattr(cls, "OPTIONS", {}).items() if len(values) > 1)
        text = _plain(cls.__doc__) + (f" (options: {opts})" if opts else "")
        star = "*" if getattr(cls, "auto_candidate", True) else ""
        rows.append((name + (" " + star if star else ""), str(k), text))
    name_w = max(len(r[0]) for r in rows)
    lines = textwrap.wrap("models (gonio fit --model NAME [--option KEY=VALUE]); k: numbers fitted, "
                          "* tried by --model auto (BIC, then a rendered check):", width, break_on_hyphens=False)
    for name, k, text in rows:
        lines += _entry(name, k, text, name_w, 2, width)
    lines += [""] + textwrap.wrap("example samples for the simulated instrument "
                                  "(gonio capture --sim --sample NAME, or a TOML file like them):", width,
                                  break_on_hyphens=False)
    samples = example_samples()
    name_w = max((len(n) for n in samples), default=4)
    for name, (path, doc) in samples.items():
        lines += _entry(name, "", f"{doc.get('description', '')} [{doc.get('model', '?')}]", name_w, 0, width)
    return lines


# --------------------------------------------------------------------------- samples
def _samples_folder():
    return resources.files("gonio.cli") / "samples"


def example_samples() -> dict[str, tuple[Path, dict]]:
    """``{name: (path, TOML document)}`` of the sample TOMLs shipped with the command line."""
    out = {}
    folder = _samples_folder()
    for entry in sorted(folder.iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".toml"):
            out[entry.name[:-5]] = (Path(str(entry)), tomllib.loads(entry.read_text(encoding="utf-8")))
    return out


def sample_path(spec):
    """``--sample``: a file that exists as given, else an example sample's name (its packaged
    TOML), else ``spec`` unchanged (load_sample then says what is wrong)."""
    if spec is None or Path(spec).exists():
        return spec
    found = example_samples().get(str(spec))
    return str(found[0]) if found else spec


# --------------------------------------------------------------------------- plans
def _error_preset_text(terms: dict) -> str:
    """The simulator's error preset in a few words: each term that is not zero."""
    parts = []
    for term, table in terms.items():
        if not isinstance(table, dict):
            continue
        on = [f"{k} {v}" for k, v in table.items()
              if not isinstance(v, str) and v not in (0, 0.0, False) and not (isinstance(v, list) and not any(v))]
        if on:
            parts.append(f"{term}: " + ", ".join(str(p).replace("True", "yes") for p in on))
    return "; ".join(parts) if parts else "no systematic errors (sensor noise only)"


def plans_lines(width: int | None = None) -> list[str]:
    """``gonio plans``: the plan presets (name, points, description), the adaptive strategy and
    plan files, and the simulated instrument's error presets."""
    from gonio.bench.plan.plans import load_plan, preset_names
    import gonio.sim.physics.errors as errors

    width = width or text_width()
    names = preset_names()
    plans = {n: load_plan(n) for n in names}
    name_w = max([len(n) for n in names] + [len("adaptive")])
    lines = textwrap.wrap("plan presets (gonio capture --plan NAME; gonio capture --plan NAME --dry-run "
                          "gives the duration):", width, break_on_hyphens=False)
    for name, plan in plans.items():
        lines += _entry(name, f"{len(plan)} pts", plan.description or "", name_w, 8, width)
    lines += _entry("adaptive", "", "chosen from the data as it is measured: the next point where the fit "
                    "learns the most (--points N, --target-rel-u X, --candidates PLAN)", name_w, 8, width)
    lines += _entry("ndf", "", "NDF-seeded: a near-retro-reflection first pass, then points drawn where the fitted "
                    "lobe sends light and is least sure (Dupuy & Jakob 2018); the same options as adaptive",
                    name_w, 8, width)
    lines += [""] + textwrap.wrap("A plan file: TOML (name, description, and points = [[theta_i, phi_i, theta_o, "
                                  "phi_o], ...] or [[scan]] tables like the presets') or CSV with the header "
                                  "theta_i,phi_i,theta_o,phi_o; angles in degrees.", width, break_on_hyphens=False)
    lines += [""] + textwrap.wrap("error presets of the simulated instrument (--errors NAME, or [errors] preset "
                                  "in the settings; gonio settings show expands them):", width,
                                  break_on_hyphens=False)
    name_w = max(len(n) for n in errors.PRESETS)
    for name, model in errors.PRESETS.items():
        terms = model.to_dict()
        terms.pop("preset", None)
        lines += _entry(name, "", _error_preset_text(terms), name_w, 0, width)
    return lines


# --------------------------------------------------------------------------- settings units
#: units a key's name or description does not carry (dimensionless numbers print "1")
_UNITS = {("holder", "sample_half"): "holder units", ("holder", "offset"): "holder units",
          ("holder", "sim_pose"): "holder units, holder units, deg", ("axes", "cycle_dist"): "microsteps/rev",
          ("camera", "pixel_size"): "holder units/pixel", ("camera", "bits"): "bits",
          ("camera", "width"): "pixels", ("camera", "height"): "pixels",
          ("camera", "gain_e_per_dn"): "e-/DN", ("camera", "read_noise_e"): "e- rms",
          ("capture", "flat_frames"): "frames", ("meter", "averaging"): "samples",
          ("lamp", "device"): "Zaber address", ("stray", "floor"): "1/sr per unit irradiance"}
_SUFFIX = (("_deg_per_s2", "deg/s^2"), ("_deg_per_s", "deg/s"), ("_deg2", "deg^2"), ("_deg", "deg"), ("_nm", "nm"),
           ("_px", "pixels"), ("_s", "s"), ("_e", "e-"))


def unit_of(section: str, key: str, value) -> str | None:
    """The unit ``gonio settings show`` prints for ``[section] key``: from the settings
    schema's description or the key's name (``_deg``, ``_s``, ...), "1" for other numbers,
    None for text, switches and tables."""
    from gonio.bench.settings import SCHEMA

    if isinstance(value, (str, bool, dict)) or value is None:
        return None
    if (section, key) in _UNITS:
        return _UNITS[(section, key)]
    desc = SCHEMA.get(section, {}).get(key, "")
    if section in ("axes", "motion") and desc.startswith("["):           # [device, axis, min_deg, max_deg]
        return ", ".join(part if part in ("device", "axis") else unit_of(section, part, 0.0)
                         for part in (p.strip() for p in desc.strip("[]").split(",")))
    for suffix, unit in _SUFFIX:
        if key.endswith(suffix):
            return unit
    m = re.search(r"\(([^()]*)\)\s*$", desc)
    if m and m.group(1) in ("s", "deg", "nm", "pixels", "electrons rms"):
        return m.group(1)
    return "1"


def _comment_lines(line: str) -> list[str]:
    """A table header or comment longer than 80 columns, its comment wrapped into ``#`` lines
    (a value line is left whole: TOML text cannot be cut)."""
    head, sep, comment = line.partition("# ")
    if len(line) <= MAX_WIDTH or not sep or " = " in head:
        return [line]
    lines = textwrap.wrap(comment, MAX_WIDTH - len(head) - 2, break_on_hyphens=False, break_long_words=False)
    return [f"{head}# {lines[0]}"] + [f"{' ' * len(head)}# {rest}" for rest in lines[1:]]


_LINE = re.compile(r"^(?P<key>[A-Za-z_]\w*) = (?P<value>.*?)  # (?P<source>default|option|file .+|preset \S+)$")


def settings_lines_with_units(lines: list[str]) -> list[str]:
    """``show_settings``' lines with each value's unit before its source: ``settle_s = 0.2  #
    s; default``, ``axes.yaw = [1, 1, -95.0, 95.0]  # 1, 1, deg, deg; default``."""
    import json

    out, section = [], None
    for line in lines:
        head = re.match(r"^\[(?P<section>[\w.]+)\]", line)
        if head:
            section = head.group("section").split(".")[-1] if head.group("section").startswith("errors.") \
                else head.group("section")
            out += _comment_lines(line)
            continue
        m = _LINE.match(line)
        if not m or section is None:
            out += _comment_lines(line)
            continue
        try:
            value = json.loads(m.group("value").replace(" = ", ": ")) if m.group("value")[:1] != "{" else {}
        except ValueError:
            value = None
        while isinstance(value, list):          # a vector or a table of numbers: its numbers' unit
            value = value[0] if value else None
        unit = unit_of(section, m.group("key"), value)
        out.append(line if unit is None else f"{m.group('key')} = {m.group('value')}  # {unit}; {m.group('source')}")
    return out
