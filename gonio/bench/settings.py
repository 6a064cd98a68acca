"""Instrument settings: the defaults in ``instrument.toml`` merged with a user's overrides.

Every table and key a settings file may hold is declared once in :data:`SCHEMA` (with what it
means); a file with an unknown table or key (``[refrence]``, ``reflectanse = 0.5``) is refused
with one line that suggests the closest known name (:func:`difflib.get_close_matches`), so a
misspelling never silently leaves the default in force. :func:`effective_settings` says where
each value came from (``default``: instrument.toml, ``file``: the user's file, ``option``: a
command-line option such as ``--operator``); ``gonio settings show`` prints it.
"""

from __future__ import annotations

import copy
import difflib
import json
import math
import tomllib
from pathlib import Path
from typing import Any, Mapping

from gonio.core.errors import GonioError

__all__ = ["DEFAULT_SETTINGS_PATH", "SCHEMA", "OPEN_SECTIONS", "default_settings", "load_settings", "merge_settings",
           "validate_settings", "check_schema", "effective_settings", "show_settings", "AXES"]

DEFAULT_SETTINGS_PATH = Path(__file__).with_name("instrument.toml")
AXES = ("yaw", "tilt", "azimuth", "lamp")   # the order of a stage-angle vector everywhere

_AXIS = "[device, axis, min_deg, max_deg]"
_MOTION = "[maxspeed_deg_per_s, accel_deg_per_s2]"
#: every table and key a settings file may hold; a new setting is declared here (one line)
SCHEMA: dict[str, dict[str, str]] = {
    "axes": {**{a: _AXIS for a in AXES}, "cycle_dist": "microsteps per revolution",
             "lamp_block_deg": "lamp arm blocks the detector within this angle (deg)"},
    "motion": {**{a: _MOTION for a in AXES}, "settle_s": "wait after IDLE before exposing (s)"},
    "camera": {"width": "pixels", "height": "pixels", "pixel_size": "holder units per pixel", "bits": "ADC bits",
               "gain_e_per_dn": "electrons per DN", "read_noise_e": "read noise (electrons rms)"},
    "holder": {"sample_half": "half-width of the sample square", "offset": "reference square offset",
               "holder_reflectance": "holder's diffuse reflectance", "markers": "ArUco markers or ChArUco board layout table",
               "sim_pose": "simulator only: the holder's true pose [dx, dy, rot_deg]"},
    "reference": {"reflectance": "certified reflectance (one value or R, G, B)",
                  "rel_std": "certificate's relative 1-sigma", "certificate": "certificate id (text)",
                  "rel_std_correlation": "full (default) or channel: how the certificate term is shared",
                  "factor_theta_i": "non-Lambertian factor grid (deg)", "factor_theta_o": "non-Lambertian factor grid (deg)",
                  "factor": "non-Lambertian factor table", "u_factor": "its standard uncertainty (calibration)",
                  "factor_a": "calibration fit term", "factor_b": "calibration fit term",
                  "factor_chi2": "calibration fit chi2", "factor_dof": "calibration fit dof"},
    "meter": {"wavelength_nm": "power meter wavelength (nm)", "averaging": "samples per reading",
              "sample_time_s": "seconds per averaged sample (a reading waits averaging x this)",
              "visa_library": "PyVISA library of a VISA resource (\"@py\", \"@ivi\", a path; default PyVISA's choice)"},
    "lamp": {"device": "Zaber address of the LED source", "flux": "relative LED flux",
             "drift_tolerance": "relative monitor change that pauses the capture",
             "bracket_tolerance": "monitor change within a point that re-measures it",
             "suspend_poll_s": "monitor poll while paused (s)", "suspend_timeout_s": "longest pause (s)"},
    "capture": {"exposure_min_s": "shortest exposure (s)", "exposure_max_s": "longest exposure (s)",
                "probe_s": "first exposure at each point (s)", "saturation_fraction": "saturation threshold",
                "noise_floor_snr": "SNR of the darkest pixel", "flat_frames": "flat-field frames",
                "roi_margin_px": "ROI margin (pixels)",
                "colour_chart": "capture the ColorChecker in the holder's chart slot for the colour matrix"},
    "systematics": {"zero_deg": "stage zero offsets, 1-sigma [yaw, tilt, azimuth, lamp] (deg)",
                    "holder_tilt_deg": "holder normal's tilt, 1-sigma per component (deg)",
                    "wedge_deg": "sample wedge, 1-sigma per component (deg)",
                    "repeat_deg": "per-move repeatability, 1-sigma (deg)", "backlash_deg": "lost motion (deg)",
                    "stray_floor": "stray-light floor bound", "linearity_gamma": "non-linearity bound at full scale",
                    "linearity_compressive": "the non-linearity is known to compress (true) or of unknown sign",
                    "source": "where the sizes come from (text)"},
    "session": {"sample_id": "the sample's identifier (report, session.toml)",
                "sample_description": "what the sample is (report)", "operator": "who measured (report)",
                "institution": "the laboratory: name and address (report, the dataset's institution)",
                "customer": "the customer: name and address (report)",
                "approver": "who approves the report (its signature block; gonio report --approver)",
                "approver_role": "the approver's role (gonio report --approver-role)"},
    # the conditions of the measurement the certificate states (ISO/IEC 17025 7.8.4.1 b); the
    # capture records them with the settings (session.toml, dataset.nc's settings attribute)
    "conditions": {"polarisation": "the source's and detector's polarisation state (text, e.g. unpolarised)",
                   "temperature_c": "ambient temperature during the capture (degC)",
                   "humidity_pct": "ambient relative humidity during the capture (%)"},
    # the monochromator (gonio.bench.drivers.monochromator, which checks these keys): a spectral plan needs it
    "monochromator": {"gratings": "[[grating, from_nm, to_nm], ...]: the grating used in each range",
                      "filters": "[[position, from_nm, to_nm], ...]: the order-sorting filter in each range",
                      "move_timeout_s": "longest a grating, filter or wavelength move may take (s)",
                      "tolerance_nm": "largest |WAVE? - target| accepted after a move (nm)",
                      "baudrate": "serial baud rate (9600 per the Cornerstone manuals)"},
}
#: tables whose keys their own module checks (one line each, naming the key): the simulator's
#: error model (gonio/sim/physics/errors.error_model) and the calibration's tables (gonio/bench/calibrate.py)
OPEN_SECTIONS = {"errors": "gonio.sim error model", "calibration": "gonio calibrate", "alignment": "gonio calibrate",
                 "linearity": "gonio calibrate", "aperture": "gonio calibrate", "stray": "gonio calibrate"}
_TEXT_KEYS = {("systematics", "source"), ("session", "sample_id"), ("session", "sample_description"), ("session", "operator"),
              ("reference", "certificate"), ("meter", "visa_library"), ("session", "institution"),
              ("session", "customer"), ("session", "approver"), ("session", "approver_role"),
              ("conditions", "polarisation")}
#: recorded ambient conditions: (low, high) of a plausible value
_CONDITIONS = {"temperature_c": (-50.0, 100.0), "humidity_pct": (0.0, 100.0)}


def _suggest(name: str, known, fmt: str = "{}") -> str:
    close = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.6)
    return f"did you mean {fmt.format(close[0])}? " if close else ""


def check_schema(user: Mapping[str, Any], where: str) -> None:
    """Refuse an unknown table or key of a user's settings with a did-you-mean (one line)."""
    for section, table in user.items():
        if section in OPEN_SECTIONS:
            continue
        if section not in SCHEMA:
            known = [*SCHEMA, *OPEN_SECTIONS]
            raise GonioError(f"{where}: unknown section [{section}]; {_suggest(section, known, '[{}]')}"
                             f"known sections: {', '.join(known)}")
        if not isinstance(table, Mapping):
            raise GonioError(f"{where}: {section} must be a table ([{section}] with keys), not a value")
        for key, value in table.items():
            if key not in SCHEMA[section]:
                raise GonioError(f"{where}: unknown key {key!r} in [{section}]; {_suggest(key, SCHEMA[section])}"
                                 f"known keys: {', '.join(SCHEMA[section])}")
            if (section, key) in _TEXT_KEYS and (not isinstance(value, str) or not value.strip()
                                                 or len(value) > 400 or not value.isprintable()):
                raise GonioError(f"{where}: {section}.{key} must be a line of printable text (at most 400 characters)")


def default_settings() -> dict[str, Any]:
    """Return a fresh copy of the default instrument settings (``gonio/bench/instrument.toml``)."""
    return validate_settings(tomllib.loads(DEFAULT_SETTINGS_PATH.read_text()))


def merge_settings(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``base`` updated table by table with ``override`` (one level of tables deep)."""
    out = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = {**out[key], **copy.deepcopy(dict(value))}
        else:
            out[key] = copy.deepcopy(value)
    return out


def _read_user(path: Path) -> dict[str, Any]:
    from gonio.core.tomlfile import read_toml

    if not Path(path).exists():
        raise GonioError(f"cannot read settings file {path}: no such file; check the path")
    user = read_toml(path, "settings file")
    check_schema(user, f"settings file {path}")
    return user


def load_settings(path: str | Path | None = None, options: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """Load settings: the defaults, overridden by the tables of the TOML file at ``path``, then
    by ``options`` (``{"session": {"operator": ...}}`` from command-line options).

    ``path`` may also be settings already loaded (a mapping, as the CLI hands them on): they are
    checked again and returned as a copy.

    Raises
    ------
    GonioError
        The file is missing or malformed, a table or key is unknown, or a value is invalid.
    """
    if isinstance(path, Mapping):
        check_schema(path, "instrument settings")
        return validate_settings(copy.deepcopy(dict(path)))
    return effective_settings(path, options)[0]


def effective_settings(path=None, options=None) -> tuple[dict[str, Any], dict[str, str]]:
    """(settings, {"section.key": "default" | "file PATH" | "option"}): where each value came from."""
    base = default_settings()
    source = {f"{s}.{k}": "default" for s, t in base.items() if isinstance(t, Mapping) for k in t}
    where = "instrument settings"
    if path is not None:
        user = _read_user(Path(path))
        base = merge_settings(base, user)
        source.update({f"{s}.{k}": f"file {path}" for s, t in user.items() for k in t})
        where = str(path)
    opts = {s: {k: v for k, v in t.items() if v is not None} for s, t in (options or {}).items()}
    opts = {s: t for s, t in opts.items() if t}
    if opts:
        check_schema(opts, "command-line option")
        base = merge_settings(base, opts)
        source.update({f"{s}.{k}": "option" for s, t in opts.items() for k in t})
    return validate_settings(base, where), source


def validate_settings(s: dict[str, Any], where: str = "instrument settings") -> dict[str, Any]:
    """Check the tables the bench relies on; raise a one-line GonioError naming the bad key."""
    def bad(key: str) -> GonioError:
        return GonioError(f"{where}: missing or invalid {key}; compare with {DEFAULT_SETTINGS_PATH.name}")

    def num(key: str, value, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad(key)
        if positive and not value > 0:
            raise bad(key)
        return float(value)

    try:
        for name in AXES:
            key = f"axes.{name}"
            dev, ax, lo, hi = s["axes"][name]
            if not (int(dev) >= 1 and int(ax) >= 1 and num(key, lo) < num(key, hi)):
                raise bad(key)
            key = f"motion.{name}"
            vmax, acc = s["motion"][name]
            num(key, vmax, True), num(key, acc, True)
        num("axes.cycle_dist", s["axes"]["cycle_dist"], True)
        rho = s["reference"]["reflectance"]
        rho = rho if isinstance(rho, list) else [rho]
        if len(rho) not in (1, 3) or not all(0 < num("reference.reflectance", r) <= 1.5 for r in rho):
            raise bad("reference.reflectance")
        for key in ("width", "height", "pixel_size", "bits"):
            num(f"camera.{key}", s["camera"][key], True)
        if "sample_time_s" in (s.get("meter") or {}):
            num("meter.sample_time_s", s["meter"]["sample_time_s"], True)
        for key, (lo, hi) in _CONDITIONS.items():
            if key in (s.get("conditions") or {}) and not lo <= num(f"conditions.{key}", s["conditions"][key]) <= hi:
                raise bad(f"conditions.{key} (between {lo:g} and {hi:g})")
    except KeyError as exc:
        raise bad(str(exc.args[0])) from None
    except (TypeError, ValueError):
        raise bad("[axes] or [motion] entry (lists of numbers)") from None
    return s


def show_settings(path=None, options=None) -> list[str]:
    """The effective settings as TOML-like lines, each value with where it came from."""
    settings, source = effective_settings(path, options)
    lines = []
    for section, table in settings.items():
        if not isinstance(table, Mapping):
            continue
        lines.append(f"[{section}]")
        for key, value in table.items():
            text = json.dumps(value) if not isinstance(value, (dict, list)) else json.dumps(value, separators=(", ", " = "))
            lines.append(f"{key} = {text}  # {source.get(f'{section}.{key}', 'default')}")
        lines.append("")
    lines += _preset_lines(settings.get("errors"), source)
    if "session" not in settings:
        lines.append("[session]  # not set: give --sample-id, --sample-description, --operator or a [session] table")
    return lines


def _preset_lines(errors, source) -> list[str]:
    """The simulator's error terms an ``[errors]`` preset expands to, each marked ``preset NAME``
    or, where the file overrides it, the file's."""
    if errors is None:
        return []
    try:
        import gonio.sim

        terms = gonio.sim.error_model(errors).to_dict()
    except (ValueError, TypeError) as exc:
        raise GonioError(" ".join(str(exc).split())[:300]) from None
    given = errors if isinstance(errors, Mapping) else {"preset": errors}
    name = terms.pop("preset", "ideal")
    lines = [f"# [errors] preset {name} expands to (gonio/sim/physics/errors.py):"]
    for term, table in terms.items():
        mine = given.get(term) if isinstance(given.get(term), Mapping) else {}
        lines.append(f"[errors.{term}]")
        lines += [f"{k} = {json.dumps(v)}  # {source.get('errors.' + term, 'file') if k in mine else 'preset ' + name}"
                  for k, v in table.items()]
    return lines + [""]
