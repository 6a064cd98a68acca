"""The text of a PDF that headless Chromium printed, with the printed size of every piece of
text: enough of PDF (ISO 32000) for the report's print tests to run without pypdf or poppler.

Chromium's PDF writer (Skia) stores each page's content as a Flate stream, its fonts as Type0
fonts with Identity-H encoding and a ToUnicode CMap; text is shown with ``Tj``/``TJ`` under
``Tf`` (font, size) and ``Tm`` inside a transformation (``cm``, ``q``/``Q``) that maps CSS px to
points. :func:`read` follows exactly that: the size of a glyph as printed is the ``Tf`` size
times the scale of the text matrix times the current transformation matrix.
"""

from __future__ import annotations

import math
import re
import unicodedata
import zlib

__all__ = ["read", "Page"]

_OBJ = re.compile(rb"(\d+)\s+0\s+obj\b")
_REF = rb"(\d+)\s+0\s+R"


class Page:
    def __init__(self):
        self.text = ""
        self.sizes: list[tuple[float, str]] = []      # (printed size in pt, the text shown at it)


def _objects(data: bytes) -> dict[int, tuple[bytes, bytes | None]]:
    """Object number -> (its dictionary text, its decoded stream or None)."""
    out = {}
    for m in _OBJ.finditer(data):
        num, start = int(m.group(1)), m.end()
        end = data.find(b"endobj", start)
        body = data[start:end]
        stream = None
        s = re.search(rb"stream\r?\n", body)
        if s is not None:
            head = body[:s.start()]
            length = re.search(rb"/Length\s+(\d+)(?!\s+0\s+R)", head)
            raw = body[s.end():s.end() + int(length.group(1))] if length else body[s.end():body.rfind(b"endstream")]
            if b"/FlateDecode" in head:
                try:
                    raw = zlib.decompress(raw)
                except zlib.error:
                    raw = b""
            stream, body = raw, head
            if length is None or s.end() + int(length.group(1)) > end - start:
                end = data.find(b"endobj", start + s.end() + len(raw))
        out[num] = (body, stream)
    return out


def _cmap(stream: bytes) -> dict[int, str]:
    """A ToUnicode CMap: code -> text."""
    out: dict[int, str] = {}

    def text(hexes: bytes) -> str:
        b = bytes.fromhex(hexes.decode())
        return b.decode("utf-16-be", errors="replace")

    for block in re.findall(rb"beginbfchar(.*?)endbfchar", stream, re.S):
        for src, dst in re.findall(rb"<([0-9A-Fa-f]+)>\s*<([0-9A-Fa-f]*)>", block):
            out[int(src, 16)] = text(dst)
    for block in re.findall(rb"beginbfrange(.*?)endbfrange", stream, re.S):
        for lo, hi, rest in re.findall(rb"<([0-9A-Fa-f]+)>\s*<([0-9A-Fa-f]+)>\s*(<[0-9A-Fa-f]*>|\[[^\]]*\])", block):
            lo, hi = int(lo, 16), int(hi, 16)
            if rest.startswith(b"["):
                for k, d in enumerate(re.findall(rb"<([0-9A-Fa-f]*)>", rest)):
                    out[lo + k] = text(d)
            else:
                first = bytes.fromhex(rest[1:-1].decode())
                for k in range(hi - lo + 1):
                    v = int.from_bytes(first, "big") + k
                    out[lo + k] = v.to_bytes(len(first), "big").decode("utf-16-be", errors="replace")
    return out


def _names(body: bytes, key: bytes, objs) -> dict[bytes, int]:
    """``/key << /Name N 0 R ... >>`` of a resource dictionary (followed when it is a reference)."""
    m = re.search(b"/" + key + rb"\s*(<<.*?>>|" + _REF + b")", body, re.S)
    if m is None:
        return {}
    inner = m.group(1)
    if m.group(2):
        inner = objs.get(int(m.group(2)), (b"", None))[0]
    return {name: int(n) for name, n in re.findall(rb"/([\w.+-]+)\s+" + _REF, inner)}


def _tokens(stream: bytes):
    i, n = 0, len(stream)
    while i < n:
        c = stream[i:i + 1]
        if c in b" \t\r\n\x00\x0c":
            i += 1
        elif c == b"%":
            while i < n and stream[i:i + 1] not in b"\r\n":
                i += 1
        elif c == b"<" and stream[i:i + 2] == b"<<":
            yield ("op", b"<<")
            i += 2
        elif c == b">" and stream[i:i + 2] == b">>":
            yield ("op", b">>")
            i += 2
        elif c == b"<":
            j = stream.index(b">", i)
            h = re.sub(rb"\s", b"", stream[i + 1:j])
            yield ("str", bytes.fromhex((h + b"0" * (len(h) % 2)).decode()))
            i = j + 1
        elif c == b"(":
            depth, j, out = 1, i + 1, bytearray()
            while j < n and depth:
                ch = stream[j:j + 1]
                if ch == b"\\":
                    nxt = stream[j + 1:j + 2]
                    esc = {b"n": b"\n", b"r": b"\r", b"t": b"\t", b"b": b"\b", b"f": b"\f"}
                    if nxt in esc:
                        out += esc[nxt]
                        j += 2
                    elif nxt.isdigit():
                        k = j + 1
                        while k < j + 4 and stream[k:k + 1].isdigit():
                            k += 1
                        out.append(int(stream[j + 1:k], 8) & 0xFF)
                        j = k
                    else:
                        out += nxt
                        j += 2
                    continue
                depth += ch == b"("
                depth -= ch == b")"
                if depth:
                    out += ch
                j += 1
            yield ("str", bytes(out))
            i = j
        elif c in b"[]":
            yield ("op", c)
            i += 1
        elif c == b"/":
            m = re.match(rb"/[^\s/\[\]()<>{}%]*", stream[i:])
            yield ("name", m.group(0)[1:])
            i += len(m.group(0))
        else:
            m = re.match(rb"[^\s/\[\]()<>{}%]+", stream[i:])
            word = m.group(0)
            i += len(word)
            try:
                yield ("num", float(word))
            except ValueError:
                yield ("op", word)


def _mul(a, b):
    """Matrices [a b c d e f] (PDF's row-vector convention): a then b."""
    return [a[0] * b[0] + a[1] * b[2], a[0] * b[1] + a[1] * b[3], a[2] * b[0] + a[3] * b[2],
            a[2] * b[1] + a[3] * b[3], a[4] * b[0] + a[5] * b[2] + b[4], a[4] * b[1] + a[5] * b[3] + b[5]]


def _run(stream: bytes, body: bytes, objs, fonts_cache, page: Page, ctm, depth=0):
    res = re.search(rb"/Resources\s+" + _REF, body)
    if res is not None:                     # resources by reference
        body = objs.get(int(res.group(1)), (b"", None))[0]
    fonts = _names(body, b"Font", objs)
    xobjects = _names(body, b"XObject", objs)
    stack, operands, array = [], [], None
    font, size, tm, tlm = None, 0.0, [1, 0, 0, 1, 0, 0], [1, 0, 0, 1, 0, 0]

    def show(raw: bytes):
        if font is None:
            return
        cmap = fonts_cache.setdefault(font, _font_cmap(font, objs))
        text = "".join(cmap.get(int.from_bytes(raw[k:k + 2], "big"), "") for k in range(0, len(raw) - 1, 2))
        page.text += text
        m = _mul(tm, ctm)
        scale = math.sqrt(abs(m[0] * m[3] - m[1] * m[2]))
        if text.strip():
            page.sizes.append((size * scale, text))

    for kind, v in _tokens(stream):
        if kind != "op":
            (array if array is not None else operands).append(v)
            continue
        if v == b"[":
            array = []
            continue
        if v == b"]":
            operands.append(array)
            array = None
            continue
        if v == b"q":
            stack.append(ctm)
        elif v == b"Q" and stack:
            ctm = stack.pop()
        elif v == b"cm" and len(operands) >= 6:
            ctm = _mul(operands[-6:], ctm)
        elif v == b"BT":
            tm, tlm = [1, 0, 0, 1, 0, 0], [1, 0, 0, 1, 0, 0]
            page.text += "\n"
        elif v == b"ET":
            page.text += "\n"
        elif v == b"Tf" and len(operands) >= 2:
            font, size = fonts.get(operands[-2]), operands[-1]
        elif v == b"Tm" and len(operands) >= 6:
            tm = tlm = list(operands[-6:])
        elif v in (b"Td", b"TD") and len(operands) >= 2:
            tlm = _mul([1, 0, 0, 1, operands[-2], operands[-1]], tlm)
            tm = tlm
        elif v == b"Tj" and operands and isinstance(operands[-1], bytes):
            show(operands[-1])
        elif v == b"TJ" and operands and isinstance(operands[-1], list):
            for part in operands[-1]:
                if isinstance(part, bytes):
                    show(part)
        elif v == b"Do" and operands and depth < 8:
            num = xobjects.get(operands[-1])
            xbody, xstream = objs.get(num, (b"", None))
            if xstream is not None and b"/Form" in xbody:
                mat = re.search(rb"/Matrix\s*\[([^\]]*)\]", xbody)
                m = [float(x) for x in mat.group(1).split()] if mat else [1, 0, 0, 1, 0, 0]
                _run(xstream, xbody, objs, fonts_cache, page, _mul(m, ctm), depth + 1)
        operands = []


def _font_cmap(num, objs) -> dict[int, str]:
    body = objs.get(num, (b"", None))[0]
    m = re.search(rb"/ToUnicode\s+" + _REF, body)
    stream = objs.get(int(m.group(1)), (b"", None))[1] if m else None
    return _cmap(stream or b"")


def read(data: bytes) -> list[Page]:
    """Every page of a PDF, in order, with its text and the printed size of each piece."""
    objs = _objects(data)
    root = next((n for n, (b, _) in objs.items() if re.search(rb"/Type\s*/Pages\b", b)
                 and not re.search(rb"/Parent\b", b)), None)
    order: list[int] = []

    def walk(num, depth=0):
        body = objs.get(num, (b"", None))[0]
        if re.search(rb"/Type\s*/Pages\b", body) and depth < 16:
            kids = re.search(rb"/Kids\s*\[([^\]]*)\]", body)
            for k in re.findall(_REF, kids.group(1) if kids else b""):
                walk(int(k), depth + 1)
        elif re.search(rb"/Type\s*/Page\b", body):
            order.append(num)

    if root is not None:
        walk(root)
    cache: dict = {}
    pages = []
    for num in order:
        body = objs[num][0]
        page = Page()
        contents = re.search(rb"/Contents\s*(\[[^\]]*\]|" + _REF + b")", body)
        refs = re.findall(_REF, contents.group(1)) if contents else []
        stream = b"\n".join(objs.get(int(r), (b"", b""))[1] or b"" for r in refs)
        _run(stream, body, objs, cache, page, [1, 0, 0, 1, 0, 0])
        page.text = unicodedata.normalize("NFKC", page.text)      # ligatures (fi) as their letters
        pages.append(page)
    return pages
