"""Fuzz the command line: hostile file contents (garbage bytes, random TOML, random or mutated
JSON, damaged datasets) and random option values, through ``main()`` in this process.

Every outcome must be exit status 0 or 2 (with one ``gonio: error:`` line), never an
exception or a traceback; a refusal writes nothing (the output path does not appear, and no
temporary file is left beside the inputs). Bounded: a fixed number of examples per command
family, each under a deadline, the whole module well under a minute on two cores.
"""

import contextlib
import gc
import io
import json
import os
import shutil
import sys
import tempfile
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from gonio.cli import main as cli

FUZZ = settings(max_examples=int(os.environ.get("GONIO_FUZZ_EXAMPLES", "25")), deadline=timedelta(seconds=30),
                database=None, derandomize=not os.environ.get("GONIO_FUZZ_RANDOM"), print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                       HealthCheck.data_too_large])

from gonio.bench.session.journal import _toml_value as journal_toml_value  # noqa: E402

MODELS = ["diffuse", "roughplastic", "cooktorrance", "orennayar", "roughconductor"]


# ----------------------------------------------------------------------------- content
def _toml_value(v) -> str:
    """session.toml's writer for scalars, plus inline tables (random documents nest them)."""
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return journal_toml_value(v)


def to_toml(doc: dict) -> str:
    """A TOML document: scalars first, then one [table] per dict, then [[arrays of tables]]."""
    lines, tables, arrays = [], [], []
    for k, v in doc.items():
        key = json.dumps(str(k))
        if isinstance(v, dict):
            tables.append((key, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((key, v))
        else:
            lines.append(f"{key} = {_toml_value(v)}")
    for key, table in tables:
        lines.append(f"[{key}]")
        lines += [f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in table.items()]
    for key, items in arrays:
        for table in items:
            lines.append(f"[[{key}]]")
            lines += [f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in table.items()]
    return "\n".join(lines) + "\n"


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2 ** 70), 2 ** 70),
                    st.sampled_from([0, -1, 1e-320, 1e308, 89.999999, 90, 45.0, 30, -30]))
scalars = st.one_of(numbers, st.text(max_size=12), st.booleans())
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=5), max_leaves=12)
names = st.one_of(st.sampled_from(["alpha", "int_ior", "reflectance", "diffuse_reflectance", "sigma", "eta", "k",
                                   "distribution", "nonlinear", "theta_i", "n", "kind", "points"]),
                  st.text(min_size=1, max_size=8))

sample_docs = st.fixed_dictionaries({}, optional={
    "model": st.one_of(st.sampled_from(MODELS), st.text(max_size=10), numbers),
    "options": st.dictionaries(names, values, max_size=3),
    "params": st.dictionaries(names, values, max_size=4),
})
angles = st.one_of(st.floats(-400, 400), numbers)
scan_docs = st.fixed_dictionaries({"kind": st.one_of(st.sampled_from(["in_plane", "hemisphere", "isotropic", "points"]),
                                                     st.text(max_size=6))},
                                  optional={"theta_i": st.lists(angles, max_size=4), "theta_o": st.lists(angles, max_size=4),
                                            "phi_d": st.lists(angles, max_size=3),
                                            "n": st.one_of(st.integers(-3, 60), st.sampled_from([4001, 10 ** 12, 2 ** 63])),
                                            "max_theta": angles, "reciprocal": st.booleans(),
                                            "points": st.lists(st.lists(angles, max_size=5), max_size=4)})
plan_docs = st.fixed_dictionaries({}, optional={"name": st.text(max_size=8),
                                                "points": st.lists(st.lists(angles, min_size=3, max_size=5), max_size=6),
                                                "scan": st.lists(scan_docs, max_size=2),
                                                "extra": values})
SETTINGS_KEYS = [("capture", "exposure_min_s"), ("capture", "exposure_max_s"), ("capture", "flat_frames"),
                 ("capture", "saturation_fraction"), ("camera", "width"), ("camera", "bits"), ("motion", "yaw"),
                 ("motion", "settle_s"), ("axes", "tilt"), ("lamp", "flux"), ("reference", "reflectance"),
                 ("meter", "averaging"), ("nosuch", "x")]
settings_docs = st.dictionaries(st.sampled_from(SETTINGS_KEYS), values, max_size=4).map(
    lambda d: {sec: {k: v for (s2, k), v in d.items() if s2 == sec} for (sec, _k) in d})

json_values = st.recursive(st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True), st.integers(-(2 ** 70), 2 ** 70),
                                     st.text(max_size=10)),
                           lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                   st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                           max_leaves=15)


def _mutate(doc, rng_picks):
    """Replace values at random paths of a JSON document."""
    doc = json.loads(json.dumps(doc))
    for path_pick, value in rng_picks:
        node, key = doc, None
        for step in path_pick:
            if isinstance(node, dict) and node:
                key = sorted(node)[step % len(node)]
            elif isinstance(node, list) and node:
                key = step % len(node)
            else:
                break
            if not isinstance(node[key], (dict, list)):
                break
            node = node[key]
        if key is not None and isinstance(node, (dict, list)):
            try:
                node[key] = value
            except (IndexError, KeyError, TypeError):
                pass
    return doc


mutations = st.lists(st.tuples(st.lists(st.integers(0, 50), min_size=1, max_size=4), json_values), min_size=1, max_size=4)


# ----------------------------------------------------------------------------- harness
@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """A real dataset.nc and fit.json to mutate."""
    from gonio.bench.samples import load_sample
    from gonio.bench.dataset.export import export
    from gonio.cli.fit import fit_cli
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("fuzzdata")
    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=2, progress=False)
    dataset = export(root / "session")
    fit_cli(dataset, model="diffuse", options=[], out=root / "fit.json", seed=0, loss="chi2", posterior=False)
    return {"dataset": dataset.read_bytes(), "fit": json.loads((root / "fit.json").read_text())}


class Work:
    """A fresh folder per example; the inputs written into it are remembered."""

    def __init__(self):
        self.dir = Path(tempfile.mkdtemp(prefix="gonio-fuzz-"))
        self.inputs = set()

    def put(self, name, content) -> Path:
        p = self.dir / name
        p.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8", "surrogatepass"))
        self.inputs.add(name)
        return p

    def stray(self):
        return sorted(p.name for p in self.dir.iterdir() if p.name not in self.inputs)

    def close(self):
        shutil.rmtree(self.dir, ignore_errors=True)


def run_cli(argv, out: Path | None, work: Work):
    """Run ``gonio ARGV``; check the promise: 0 or 2, one line on refusal, nothing written then."""
    err, outbuf = io.StringIO(), io.StringIO()
    ignored = []                                      # "Exception ignored in ..." would reach stderr
    previous, sys.unraisablehook = sys.unraisablehook, ignored.append
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(outbuf):
            try:
                rc = cli.main([str(a) for a in argv])
            except SystemExit as exc:                 # argparse
                rc = exc.code
            gc.collect()
    finally:
        sys.unraisablehook = previous
    text = err.getvalue()
    assert "Traceback" not in text, text
    assert not ignored, (argv, [(u.object, u.exc_value) for u in ignored])
    assert rc in (0, 2), (rc, argv, text[-2000:])
    if rc == 2:
        lines = [line for line in text.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("gonio: error:"), (argv, text)
        if out is not None:
            assert not out.exists(), (argv, text)
        assert work.stray() == [], (argv, work.stray(), text)
    return rc, text


def dataset_bytes(draw, real):
    kind = draw(st.sampled_from(["garbage", "truncated", "flipped", "real", "empty"]))
    data = real["dataset"]
    if kind == "garbage":
        return draw(st.binary(max_size=3000))
    if kind == "truncated":
        return data[: draw(st.integers(0, len(data) - 1))]
    if kind == "flipped":
        b = bytearray(data)
        for _ in range(draw(st.integers(1, 8))):
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        return bytes(b)
    if kind == "empty":
        return b""
    return data


def fit_bytes(draw, real):
    kind = draw(st.sampled_from(["garbage", "json", "mutated", "nan"]))
    if kind == "garbage":
        return draw(st.binary(max_size=500))
    if kind == "json":
        return json.dumps(draw(json_values)).encode()
    if kind == "nan":
        return json.dumps(real["fit"]).replace("0.", "NaN", 1).encode()
    return json.dumps(_mutate(real["fit"], draw(mutations))).encode()


# ----------------------------------------------------------------------------- the fuzz tests
@FUZZ
@given(data=st.data())
def test_fuzz_fit_and_convert(real, data):
    work = Work()
    try:
        ds = work.put(data.draw(st.sampled_from(["d.nc", "d.bsdf", "d.binary", "d.txt", "é d.nc"])),
                      dataset_bytes(data.draw, real))
        fit = work.put("f.json", fit_bytes(data.draw, real))
        if data.draw(st.booleans()):
            out = work.dir / data.draw(st.sampled_from(["o.json", "sub/o.json", "f.json/o.json", "d.nc", "."]))
            argv = ["fit", ds, "--model", data.draw(st.one_of(st.just("diffuse"), st.text(max_size=6))),
                    "--out", out, "--loss", data.draw(st.sampled_from(["chi2", "robust", "log", "cosine", "x"]))]
            if data.draw(st.booleans()):
                argv += ["--option", data.draw(st.text(max_size=12))]
            if data.draw(st.booleans()):
                argv += ["--seed", data.draw(st.integers(-(2 ** 64), 2 ** 64))]
        else:
            to = data.draw(st.sampled_from(["mitsuba-xml", "mitsuba-dict", "csv", "merl-data", "merl", "nosuch"]))
            src = fit if to.startswith("mitsuba") or to == "merl" else ds
            out = work.dir / data.draw(st.sampled_from(["o.out", "sub/o.out", "f.json/x", "f.json"]))
            if to == "merl" and data.draw(st.booleans()):
                to = "mitsuba-xml"
            argv = ["convert", src, "--to", to, "--out", out]
        if out.exists():
            out = None                                  # an input named as output: check only the status
        run_cli(argv, out, work)
    finally:
        work.close()


@FUZZ
@given(data=st.data())
def test_fuzz_render_options(real, data):
    work = Work()
    try:
        fit = work.put("f.json", fit_bytes(data.draw, real) if data.draw(st.booleans())
                       else json.dumps(real["fit"]).encode())
        ds = work.put("d.nc", dataset_bytes(data.draw, real))
        out = work.dir / "render"
        argv = ["render", fit, "--dataset", ds, "--out", out]
        if data.draw(st.booleans()):
            argv += ["--variant", data.draw(st.one_of(st.sampled_from(["scalar_rgb", "scalar_spectral", "cuda_ad_rgb"]),
                                                      st.text(max_size=8)))]
        if data.draw(st.booleans()):
            argv += ["--preview", "--size", data.draw(st.sampled_from([-1, 0, 7, 8, 5000, 10 ** 20])),
                     "--spp", data.draw(st.sampled_from([-1, 0, 1, 10 ** 9]))]
        if data.draw(st.booleans()):
            argv += ["--measured", work.put(data.draw(st.sampled_from(["m.bsdf", "m.binary", "m.txt"])),
                                            b"tensor_file\x00" + data.draw(st.binary(max_size=400)))]
        run_cli(argv, out, work)
    finally:
        work.close()


@FUZZ
@given(data=st.data())
def test_fuzz_plan_settings_sample(data):
    work = Work()
    try:
        def text_or_garbage(doc_strategy, name):
            if data.draw(st.integers(0, 4)) == 0:
                return work.put(name, data.draw(st.binary(max_size=400)))
            return work.put(name, to_toml(data.draw(doc_strategy)))

        out = work.dir / "session"
        which = data.draw(st.sampled_from(["plan", "settings", "sample", "csv"]))
        argv = ["capture", "--sim", "--out", out, "--quiet", "--plan", "quick"]
        if which == "plan":
            argv += ["--plan", text_or_garbage(plan_docs, "p.toml"), "--dry-run"]
        elif which == "csv":
            rows = data.draw(st.lists(st.lists(st.one_of(numbers, st.text(max_size=4)), max_size=5), max_size=6))
            header = data.draw(st.sampled_from(["theta_i,phi_i,theta_o,phi_o", "a,b", ""]))
            body = "\n".join(",".join(str(x) for x in r) for r in rows)
            argv += ["--plan", work.put("p.csv", header + "\n" + body), "--dry-run"]
        elif which == "settings":
            argv += ["--settings", text_or_garbage(settings_docs, "s.toml"), "--dry-run"]
        else:
            one = work.put("one.toml", 'name = "one"\npoints = [[30, 0, 30, 180]]\n')
            argv += ["--sample", text_or_garbage(sample_docs, "sample.toml"), "--plan", one]
        rc, text = run_cli(argv, out, work)
        if "--dry-run" in argv:
            assert not out.exists()
    finally:
        work.close()


@FUZZ
@given(data=st.data())
def test_fuzz_batch_and_small_commands(real, data):
    work = Work()
    try:
        kind = data.draw(st.sampled_from(["workers", "scheduler", "bench", "clock"]))
        out = work.dir / "batch"
        ds = work.put("d.nc", real["dataset"])
        if kind == "workers":
            argv = ["fit", "--batch", ds, "--model", "diffuse", "--out", out, "--workers",
                    data.draw(st.one_of(st.integers(-(2 ** 40), 0), st.integers(10 ** 4, 2 ** 64)))]
        elif kind == "scheduler":
            from gonio.fitting.batch.dask_batch import check_scheduler_address

            address = data.draw(st.text(max_size=30))
            try:
                check_scheduler_address(address)
                assume(False)                           # a well-formed address would be dialled
            except ValueError:
                pass
            argv = ["fit", "--batch", ds, "--model", "diffuse", "--out", out, "--scheduler", address]
        elif kind == "bench":
            out = None
            argv = ["bench", "models", "-n", data.draw(st.one_of(st.integers(-(2 ** 40), 999),
                                                              st.integers(10 ** 7 + 1, 2 ** 64)))]
        else:
            out = None
            clock = data.draw(st.one_of(st.sampled_from(["-1", "0", "nan", "inf", "1e400", "-inf", "1e-9"]),
                                        st.text(max_size=6)))
            assume(clock.strip().lower() not in ("instant", "realtime", "real"))
            try:
                assume(not (1e-6 <= float(clock) <= 1e6))
            except ValueError:
                pass
            argv = ["sim", "serve", "--clock", clock]
        rc, _ = run_cli(argv, out, work)
        assert rc == 2
    finally:
        work.close()
