"""Fuzz the readers of what a user gives, one layer below the CLI (issue 36): TOML (the checked
parser, samples, plans), a Mitsuba scene file (:mod:`gonio.fitting.selection.scene_file`), a fit
file (``parse_fit``, ``load_fit``) and a damaged dataset.nc (zeroed blocks, flipped bytes,
truncation; ``open_dataset`` with its HDF5 walk in a child, then ``open_budget``).

The property everywhere: an input is read, or refused with the reader's one-line error
(GonioError; ValueError for the fit file's parser) -- never another exception, never a hang
(each example under a deadline; a damaged dataset.nc whose HDF5 walk loops costs
check_hdf5's 20 s, so the long runs may take an hour). The default run draws a fixed, small set of examples
(derandomized, ~20 s in all); ``pytest -m long`` (``make test-long``) draws many more.
"""

import json
import struct
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gonio.core.errors import GonioError

COMMON = dict(database=None, derandomize=True, print_blob=True, deadline=timedelta(seconds=30),
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                     HealthCheck.data_too_large, HealthCheck.filter_too_much])
FAST, LONG = settings(max_examples=100, **COMMON), settings(max_examples=1500, **COMMON)
FAST_NC, LONG_NC = settings(max_examples=6, **COMMON), settings(max_examples=200, **COMMON)


def one_line(exc: BaseException) -> None:
    text = str(exc)
    assert text.strip() and "\n" not in text and "Traceback" not in text, repr(text)


def mutated(data: st.DataObject, text: str, alphabet: str) -> str:
    """``text`` with a few characters inserted, deleted or replaced, or cut short."""
    for _ in range(data.draw(st.integers(1, 6))):
        i = data.draw(st.integers(0, len(text)))
        op = data.draw(st.sampled_from(["insert", "delete", "replace", "cut"]))
        piece = data.draw(st.text(alphabet=alphabet, max_size=12) | st.sampled_from(SPICE))
        if op == "insert":
            text = text[:i] + piece + text[i:]
        elif op == "delete":
            text = text[:i] + text[i + data.draw(st.integers(1, 20)):]
        elif op == "replace":
            text = text[:i] + piece + text[i + len(piece):]
        else:
            text = text[:i]
    return text


SPICE = ["nan", "inf", "-inf", "1e400", "-1", "0", "99999999999999999999999", "\x00", "\ud800", "[[", "]]", "{",
         '"', "'''", "\\u0000", "=", "\n[x]\n", "&x;", "<!DOCTYPE x>", "/etc/passwd", "../../", "$x", "<include filename='x'/>"]

# ----------------------------------------------------------------------------- TOML
SAMPLE = '''model = "roughplastic"
[options]
distribution = "ggx"
[params]
diffuse_reflectance = [0.5, 0.3, 0.2]
alpha = 0.2
int_ior = 1.5
'''
PLAN = '''name = "fuzz"
points = [[30, 0, 30, 180], [45.0, 0, 20, 180]]
[[scan]]
kind = "in_plane"
theta_i = [10, 40]
n = 5
'''
TOML_ALPHABET = st.characters(codec="utf-8", exclude_categories=["Cs"])


def check_toml(data, tmp_path):
    from gonio.bench.plan.plans import load_plan
    from gonio.bench.samples import load_sample
    from gonio.core.tomlfile import parse_toml

    base = data.draw(st.sampled_from([SAMPLE, PLAN]))
    if data.draw(st.integers(0, 5)) == 0:
        text = data.draw(st.text(TOML_ALPHABET, max_size=200))
    else:
        text = mutated(data, base, "0123456789.,=[]{}\"'\n abcdexyz_-+")
    try:
        parse_toml(text, "fuzz")
    except GonioError as exc:
        one_line(exc)
    path = tmp_path / data.draw(st.sampled_from(["s.toml", "p.toml"]))
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    for reader in (load_sample, load_plan):
        try:
            reader(path)
        except GonioError as exc:
            one_line(exc)


@FAST
@given(data=st.data())
def test_fuzz_toml(tmp_path, data):
    check_toml(data, tmp_path)


@pytest.mark.long
@pytest.mark.timeout(3600)
@LONG
@given(data=st.data())
def test_fuzz_toml_long(tmp_path, data):
    check_toml(data, tmp_path)


# ----------------------------------------------------------------------------- scene XML
TAGS = ["scene", "shape", "bsdf", "include", "string", "integer", "float", "film", "sensor", "sampler", "integrator",
        "default", "path", "texture", "emitter", "transform", "ref", "rgb"]
ATTRS = ["type", "id", "name", "value", "filename", "version"]
VALUES = ["wall.ply", "sub/inc.xml", "/etc/passwd", "../../etc/passwd", "etc/passwd", "zero.ply", "fifo.ply",
          "empty.ply", "small.png", "nosuch.ply", "$x", "$f.ply", "", "filename", "sample", "ply", "serialized",
          "width", "height", "sample_count", "max_depth", "rr_depth", "-1", "0", "8", "100000", "1e9", "x", "3.0.0",
          "hdrfilm", "bitmap", "diffuse", "~/x", "sub/../wall.ply", "sub", "."]


def _element(draw, depth):
    tag = draw(st.sampled_from(TAGS))
    attrs = draw(st.dictionaries(st.sampled_from(ATTRS), st.sampled_from(VALUES), max_size=3))
    children = draw(st.lists(st.deferred(lambda: elements(depth + 1)), max_size=3)) if depth < 4 else []
    a = "".join(f' {k}="{v}"' for k, v in attrs.items())
    return f"<{tag}{a}>" + "".join(children) + f"</{tag}>"


def elements(depth=0):
    return st.composite(lambda draw: _element(draw, depth))()


VALID_SCENE = """<scene version="3.0.0"><integrator type="direct"/>
<shape type="sphere"><bsdf type="diffuse" id="sample"/></shape>
<shape type="ply"><string name="filename" value="wall.ply"/></shape>
<include filename="sub/inc.xml"/>
<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
</film><sampler type="independent"><integer name="sample_count" value="4"/></sampler></sensor></scene>"""


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    import os

    d = tmp_path_factory.mktemp("scenefuzz")
    (d / "sub").mkdir()
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    (d / "wall.ply").write_bytes(head + struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack("<B3i", 3, 0, 1, 2))
    (d / "sub" / "inc.xml").write_text('<scene version="3.0.0"><shape type="ply" filename="wall.ply"/></scene>')
    (d / "empty.ply").write_bytes(b"")
    (d / "small.png").write_bytes(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">II", 4, 4))
    os.symlink("/etc", d / "etc")
    os.symlink("/dev/zero", d / "zero.ply")
    os.mkfifo(d / "fifo.ply")
    return d


def check_scene(data, folder):
    from gonio.fitting.selection.scene_file import checked_scene

    kind = data.draw(st.sampled_from(["grammar", "mutated", "bytes"]))
    if kind == "grammar":
        body = "".join(data.draw(st.lists(elements(1), max_size=5)))
        text = (f'<scene version="3.0.0">{body}</scene>').encode()
    elif kind == "mutated":
        text = mutated(data, VALID_SCENE, "<>/=\"' abcdefghilmnoprstuvwxyz0123456789$&;#").encode("utf-8",
                                                                                                 "surrogatepass")
    else:
        raw = bytearray(VALID_SCENE.encode())
        for _ in range(data.draw(st.integers(1, 8))):
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
        text = bytes(raw)
    path = folder / "fuzz.xml"
    path.write_bytes(text)
    try:
        root = checked_scene(path)
    except GonioError as exc:
        one_line(exc)
        return
    real = str(folder.resolve())
    for el in root.iter():
        for attr, value in el.attrib.items():
            if attr == "filename" or (el.tag == "string" and attr == "value"
                                      and (el.get("name") or "").lower().endswith("filename")):
                assert value.startswith(real + "/") and Path(value).is_file(), value
        assert el.tag not in ("include", "path", "default")


@FAST
@given(data=st.data())
def test_fuzz_scene_file(scene_folder, data):
    check_scene(data, scene_folder)


@pytest.mark.long
@pytest.mark.timeout(3600)
@LONG
@given(data=st.data())
def test_fuzz_scene_file_long(scene_folder, data):
    check_scene(data, scene_folder)


# ----------------------------------------------------------------------------- fit file
FIT = {"format": "gonio-fit/1", "model": {"name": "roughplastic", "options": {"distribution": "ggx"}},
       "params": {"diffuse_reflectance": [0.5, 0.3, 0.2], "alpha": 0.2, "int_ior": 1.5},
       "quality": {"chi2_red": 1.1, "n": 30}, "seed": 0}
json_values = st.recursive(st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True),
                                     st.integers(-(2 ** 70), 2 ** 70), st.text(max_size=8)),
                           lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                   st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                           max_leaves=12)


def _replace(doc, path, value):
    node = doc
    for step in path[:-1]:
        keys = sorted(node) if isinstance(node, dict) else range(len(node))
        if not keys:
            return
        key = list(keys)[step % len(keys)]
        if not isinstance(node[key], (dict, list)):
            break
        node = node[key]
    keys = list(sorted(node) if isinstance(node, dict) else range(len(node)))
    if keys:
        node[keys[path[-1] % len(keys)]] = value


def check_fit(data, tmp_path):
    from gonio.fitting.formats.fitfile import load_fit, parse_fit

    doc = json.loads(json.dumps(FIT))
    for _ in range(data.draw(st.integers(0, 4))):
        _replace(doc, data.draw(st.lists(st.integers(0, 20), min_size=1, max_size=3)), data.draw(json_values))
    try:
        parse_fit(doc, "fuzz.json")
    except ValueError as exc:
        one_line(exc)
    text = json.dumps(doc)
    if data.draw(st.booleans()):
        text = mutated(data, text, '{}[]":,0123456789.eE-+ abcnNIulfrst')
    path = tmp_path / "fit.json"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    try:
        load_fit(path)
    except ValueError as exc:
        one_line(exc)


@FAST
@given(data=st.data())
def test_fuzz_fit_file(tmp_path, data):
    check_fit(data, tmp_path)


@pytest.mark.long
@pytest.mark.timeout(3600)
@LONG
@given(data=st.data())
def test_fuzz_fit_file_long(tmp_path, data):
    check_fit(data, tmp_path)


# ----------------------------------------------------------------------------- dataset.nc
@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("ncfuzz")
    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=2, progress=False)
    return export(root / "session").read_bytes()


def check_dataset(data, dataset, tmp_path):
    from gonio.bench.dataset.reader import open_budget, open_dataset

    raw = bytearray(dataset)
    kind = data.draw(st.sampled_from(["zeroed", "flipped", "truncated", "block"]))
    if kind == "zeroed":                # whole 512-byte blocks zeroed (a bad sector)
        for _ in range(data.draw(st.integers(1, 3))):
            i = data.draw(st.integers(0, len(raw) // 512 - 1)) * 512
            raw[i:i + 512] = bytes(512)
    elif kind == "flipped":
        for _ in range(data.draw(st.integers(1, 16))):
            raw[data.draw(st.integers(0, len(raw) - 1))] ^= 1 << data.draw(st.integers(0, 7))
    elif kind == "truncated":
        raw = raw[:data.draw(st.integers(0, len(raw) - 1))]
    else:                               # a block of random bytes
        i = data.draw(st.integers(0, len(raw) - 1))
        chunk = data.draw(st.binary(min_size=1, max_size=256))
        raw[i:i + len(chunk)] = chunk
    path = tmp_path / "dataset.nc"
    path.write_bytes(bytes(raw))
    try:
        meas = open_dataset(path)
        open_budget(path, meas)
    except GonioError as exc:
        one_line(exc)


@FAST_NC
@given(data=st.data())
def test_fuzz_damaged_dataset(dataset, tmp_path, data):
    check_dataset(data, dataset, tmp_path)


@pytest.mark.long
@pytest.mark.timeout(3600)
@LONG_NC
@given(data=st.data())
def test_fuzz_damaged_dataset_long(dataset, tmp_path, data):
    check_dataset(data, dataset, tmp_path)

