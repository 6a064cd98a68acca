"""A user's Mitsuba scene file, checked before Mitsuba reads it: confined to its folder, bounded.

:func:`checked_scene` parses the file with expat refusing any DOCTYPE (so no entity expansion,
no external entity), inlines its ``<include>`` files (at most :data:`MAX_INCLUDE_DEPTH` deep),
substitutes its ``<default>`` parameters, and checks every file the scene names (a
``filename`` attribute, a ``<string name="...filename">``): a relative path that stays inside
the scene's folder once symlinks are resolved, a regular file of bounded size; a PLY, image or
grid volume whose header declares no more than the file can hold and no more than
:data:`MAX_IMAGE_PIXELS` pixels. ``<path>`` (which widens Mitsuba's search path) and
``serialized`` meshes (zlib streams of unbounded size) are refused. Films, samples per pixel
and path depths are bounded. It returns the tree with every path made absolute, so Mitsuba
reads exactly the files checked; anything else is a :class:`GonioError` of one line. The
render's time is bounded by the caller (``gonio fit --scene`` renders in a child process with
a deadline, :mod:`gonio.core.deadline`).
"""

from __future__ import annotations

import os
import pyexpat
import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

from gonio.core.errors import GonioError
from gonio.core.preflight import MiB, check_input_file

__all__ = ["checked_scene", "check_scene_file", "MAX_XML_BYTES", "MAX_FILE_BYTES", "MAX_TOTAL_BYTES",
           "MAX_INCLUDE_DEPTH", "MAX_ELEMENTS", "MAX_NESTING", "MAX_FILM_SIDE", "MAX_FILM_PIXELS", "MAX_SPP", "MAX_DEPTH",
           "MAX_IMAGE_PIXELS"]

MAX_XML_BYTES = 4 * MiB          # one scene or include file
MAX_FILE_BYTES = 256 * MiB       # one mesh, texture, volume or measured BSDF
MAX_TOTAL_BYTES = 1024 * MiB     # all the files a scene names
MAX_INCLUDE_DEPTH = 8
MAX_ELEMENTS = 100_000
MAX_NESTING = 100
MAX_FILM_SIDE = 4096
MAX_FILM_PIXELS = 4096 * 4096
MAX_SPP = 1 << 16
MAX_DEPTH = 64                   # an integrator's max_depth and rr_depth
MAX_IMAGE_PIXELS = 8192 * 4096   # a texture or an environment map
_PARAM = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


def check_scene_file(path) -> None:
    """GonioError (one line) unless ``path`` passes :func:`checked_scene`."""
    checked_scene(path)


def checked_scene(path) -> ET.Element:
    """The scene file ``path`` checked (see the module): its root ``<scene>`` element with
    includes inlined, defaults substituted and every file path absolute."""
    path = Path(path)
    folder = Path(os.path.realpath(path.parent if str(path.parent) else "."))
    root = _parse(path, "scene file")
    if root.tag != "scene":
        raise GonioError(f"scene {path}: the root element is <{root.tag[:40]}>, not a Mitsuba <scene>")
    _inline_includes(root, folder, path, depth=0)
    count = sum(1 for _ in root.iter())
    if count > MAX_ELEMENTS:
        raise GonioError(f"scene {path} has {count} elements with its includes; at most {MAX_ELEMENTS} are read")
    _substitute_defaults(root, path)
    total = 0
    parents = {c: p for p in root.iter() for c in p}
    for el in root.iter():
        if el.tag == "path":
            raise GonioError(f"scene {path}: <path> widens where Mitsuba looks for files; remove it and keep the "
                             "scene's files in its folder")
        if el.tag == "shape" and el.get("type") == "serialized":
            raise GonioError(f"scene {path}: a 'serialized' mesh is a compressed stream of any size; convert it to "
                             "PLY or OBJ")
        for attr, value in list(el.attrib.items()):
            if attr == "filename" or (el.tag == "string" and attr == "value"
                                      and (el.get("name") or "").lower().endswith("filename")):
                owner = el if attr == "filename" else parents.get(el, el)
                real = _confined(value, folder, path)
                total += _check_referenced(real, owner, path)
                if total > MAX_TOTAL_BYTES:
                    raise GonioError(f"scene {path} names files of more than {MAX_TOTAL_BYTES // MiB} MiB in all; "
                                     "give a smaller scene")
                el.set(attr, real)
    _check_bounds(root, path)
    return root


# ----------------------------------------------------------------------------- parsing
class _Refused(Exception):
    pass


def _parse(path: Path, what: str) -> ET.Element:
    """``path`` as an element tree; expat with any DOCTYPE refused (so no entity is declared or
    expanded), elements nested at most :data:`MAX_NESTING` deep."""
    path = check_input_file(path, what, max_bytes=MAX_XML_BYTES)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise GonioError(f"cannot read {what} {path} ({exc.strerror}); check the path") from None
    tb, depth = ET.TreeBuilder(), [0]

    def start(tag, attrs):
        depth[0] += 1
        if depth[0] > MAX_NESTING:
            raise _Refused(f"{what} {path} nests elements more than {MAX_NESTING} deep; fix the file")
        tb.start(tag, attrs)

    def end(tag):
        depth[0] -= 1
        tb.end(tag)

    def doctype(*_args):
        raise _Refused(f"{what} {path} declares a DOCTYPE or entities; a Mitsuba scene has none, remove it")

    p = pyexpat.ParserCreate()
    p.StartElementHandler, p.EndElementHandler, p.CharacterDataHandler = start, end, tb.data
    p.StartDoctypeDeclHandler = p.EntityDeclHandler = p.ExternalEntityRefHandler = doctype
    try:
        p.Parse(data, True)
        return tb.close()
    except _Refused as exc:
        raise GonioError(str(exc)) from None
    except (pyexpat.ExpatError, AssertionError) as exc:
        raise GonioError(f"{what} {path}: not a readable XML file ({' '.join(str(exc).split())[:120]})") from None


def _confined(value: str, folder: Path, path: Path) -> str:
    """``value`` (a path the scene names) as an absolute real path inside ``folder``."""
    shown = repr(value[:80])
    if not value or "\x00" in value:
        raise GonioError(f"scene {path} names the file {shown}; give a file name relative to the scene's folder")
    if os.path.isabs(value) or value.startswith("~"):
        raise GonioError(f"scene {path} names the file {shown} by an absolute path; a scene reads only files in "
                         "its own folder: copy the file there and give its relative name")
    real = os.path.realpath(folder / value)
    if os.path.commonpath([real, str(folder)]) != str(folder):
        raise GonioError(f"scene {path} names the file {shown}, which lies outside the scene's folder {folder} "
                         "(through '..' or a symbolic link); a scene reads only files in its own folder")
    return real


def _inline_includes(el: ET.Element, folder: Path, path: Path, depth: int) -> None:
    for i, child in reversed(list(enumerate(el))):
        if child.tag == "include":
            if depth >= MAX_INCLUDE_DEPTH:
                raise GonioError(f"scene {path} nests <include> more than {MAX_INCLUDE_DEPTH} deep; flatten it")
            real = _confined(child.get("filename") or "", folder, path)
            inc = _parse(Path(real), f"scene {path}: the included file")
            if inc.tag != "scene":
                raise GonioError(f"scene {path}: the included file {child.get('filename')!r:.80} is not a <scene>")
            _inline_includes(inc, folder, path, depth + 1)
            el[i:i + 1] = list(inc)
        else:
            _inline_includes(child, folder, path, depth)


def _substitute_defaults(root: ET.Element, path: Path) -> None:
    defaults = {}
    for el in list(root.iter("default")):
        defaults.setdefault(el.get("name", ""), el.get("value", ""))
    for p in list(root.iter()):
        for child in [c for c in p if c.tag == "default"]:
            p.remove(child)

    def sub(m):
        if m.group(1) not in defaults:
            raise GonioError(f"scene {path} uses the parameter ${m.group(1)[:40]} without a <default> for it; "
                             "add one")
        return defaults[m.group(1)]

    for el in root.iter():
        for attr, value in el.attrib.items():
            if "$" in value:
                el.set(attr, _PARAM.sub(sub, value))


# ----------------------------------------------------------------------------- referenced files
def _check_referenced(real: str, owner: ET.Element, path: Path) -> int:
    """Check one file the scene names; its size in bytes."""
    name = os.path.basename(real)
    f = check_input_file(real, f"scene {path}: the file", max_bytes=MAX_FILE_BYTES)
    size = f.stat().st_size
    with open(f, "rb") as fh:
        head = fh.read(64 * 1024)
    what = f"scene {path}: the file {name!r:.80}"
    kind = owner.get("type", "")
    if head.startswith(b"ply") or (owner.tag == "shape" and kind == "ply"):
        _check_ply(head, size, what)
    elif head[:2] == b"\x1c\x04" or (owner.tag == "shape" and kind == "serialized"):
        raise GonioError(f"{what} is a 'serialized' mesh (a compressed stream of any size); convert it to PLY or OBJ")
    elif head.startswith(b"VOL"):
        _check_vol(head, size, what)
    else:
        dims = _image_size(head)
        if dims is not None:
            w, h = dims
            if not (0 < w and 0 < h and w * h <= MAX_IMAGE_PIXELS):
                raise GonioError(f"{what} is an image of {w} x {h} pixels; give one of at most "
                                 f"{MAX_IMAGE_PIXELS // 1_000_000} million pixels")
        elif owner.tag in ("texture", "emitter"):
            raise GonioError(f"{what} is not an image gonio can check (PNG, JPEG, OpenEXR, RGBE .hdr or PFM); "
                             "convert it to one of those")
    return size


_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_ply(head: bytes, size: int, what: str) -> None:
    """The header's element counts must fit in the file (each row at least its fixed bytes)."""
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise GonioError(f"{what} is not a PLY file with a header of at most 64 KiB; give a PLY mesh")
    lines = head[:end].decode("ascii", "replace").splitlines()
    body = size - (head.find(b"\n", end) + 1)
    fmt, need, rows, row = None, 0, 0, 0
    try:
        for line in lines[1:]:
            w = line.split()
            if not w or w[0] in ("comment", "obj_info"):
                continue
            if w[0] == "format":
                fmt = w[1]
            elif w[0] == "element":
                need += rows * row
                rows, row = int(w[2]), 0
                if not 0 <= rows <= 1 << 31:
                    raise ValueError
            elif w[0] == "property":
                if w[1] == "list":
                    row += _PLY_SIZES[w[2]] if fmt != "ascii" else 2
                else:
                    row += _PLY_SIZES[w[1]] if fmt != "ascii" else 2
        need += rows * row
    except (ValueError, IndexError, KeyError):
        raise GonioError(f"{what} has a malformed PLY header; give a PLY mesh") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise GonioError(f"{what} has no PLY format line; give a PLY mesh")
    if need > body or (rows and not row):
        raise GonioError(f"{what} declares more elements than its {size} bytes hold; give an undamaged PLY mesh")


def _check_vol(head: bytes, size: int, what: str) -> None:
    if len(head) < 48:
        raise GonioError(f"{what} is a truncated grid volume; give an undamaged .vol file")
    x, y, z, c = struct.unpack("<4i", head[8:24])
    if min(x, y, z, c) < 1 or x * y * z * c * 4 + 48 > size:
        raise GonioError(f"{what} declares a {x} x {y} x {z} x {c} grid its {size} bytes cannot hold; give an "
                         "undamaged .vol file")


def _image_size(head: bytes):
    """(width, height) from an image header (PNG, JPEG, OpenEXR, RGBE, PFM); None if none of
    those; (0, 0) where the header is one of those but unreadable."""
    try:
        if head.startswith(b"\x89PNG\r\n\x1a\n"):
            return struct.unpack(">II", head[16:24])
        if head.startswith(b"\xff\xd8"):
            i = 2
            while i + 9 < len(head):
                if head[i] != 0xFF:
                    return 0, 0
                marker, length = head[i + 1], struct.unpack(">H", head[i + 2:i + 4])[0]
                if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                    h, w = struct.unpack(">HH", head[i + 5:i + 9])
                    return w, h
                i += 2 + length
            return 0, 0
        if head.startswith(b"\x76\x2f\x31\x01"):
            i = 8
            while i < len(head) and head[i] != 0:
                name_end = head.index(b"\x00", i)
                type_end = head.index(b"\x00", name_end + 1)
                n = struct.unpack("<i", head[type_end + 1:type_end + 5])[0]
                if head[i:name_end] == b"dataWindow":
                    x0, y0, x1, y1 = struct.unpack("<4i", head[type_end + 5:type_end + 21])
                    return x1 - x0 + 1, y1 - y0 + 1
                i = type_end + 5 + n
            return 0, 0
        if head.startswith(b"#?"):
            for line in head.split(b"\n")[1:64]:
                m = re.fullmatch(rb"[-+]Y (\d+) [-+]X (\d+)", line.strip())
                if m:
                    return int(m.group(2)), int(m.group(1))
            return 0, 0
        if head[:3] in (b"PF\n", b"Pf\n"):
            w, h = head[3:64].split()[:2]
            return int(w), int(h)
    except (struct.error, ValueError):
        return 0, 0
    return None


# ----------------------------------------------------------------------------- bounds
def _int(el: ET.Element, path: Path) -> int:
    try:
        return int(el.get("value", ""))
    except ValueError:
        raise GonioError(f"scene {path}: <integer name={el.get('name')!r:.40}> has the value "
                         f"{el.get('value')!r:.40}, not an integer") from None


def _check_bounds(root: ET.Element, path: Path) -> None:
    for film in root.iter("film"):
        side = {c.get("name"): _int(c, path) for c in film.findall("integer") if c.get("name") in ("width", "height")}
        for name, v in side.items():
            if not 1 <= v <= MAX_FILM_SIDE:
                raise GonioError(f"scene {path}: the film's {name} {v}; give 1 to {MAX_FILM_SIDE} pixels")
        if side.get("width", 1) * side.get("height", 1) > MAX_FILM_PIXELS:
            raise GonioError(f"scene {path}: the film has more than {MAX_FILM_PIXELS} pixels; make it smaller")
    for sampler in root.iter("sampler"):
        for c in sampler.findall("integer"):
            if c.get("name") == "sample_count" and not 1 <= _int(c, path) <= MAX_SPP:
                raise GonioError(f"scene {path}: the sampler's sample_count {c.get('value')}; give 1 to {MAX_SPP}")
    for integrator in root.iter("integrator"):
        for c in integrator.iter("integer"):
            if c.get("name") in ("max_depth", "rr_depth"):
                v = _int(c, path)
                if not (-1 <= v <= MAX_DEPTH) or (v == -1 and c.get("name") == "rr_depth"):
                    raise GonioError(f"scene {path}: the integrator's {c.get('name')} {v}; give 1 to {MAX_DEPTH} "
                                     "(max_depth may be -1, unbounded, with Russian roulette from rr_depth)")
