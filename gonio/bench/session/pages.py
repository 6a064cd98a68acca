"""Table rows read straight from an SQLite database file's pages, without SQLite.

For a journal SQLite can no longer open or walk (a damaged header page, schema or b-tree
interior page): every table b-tree leaf page of the file, and every page image in its
``-wal``, is parsed on its own (https://www.sqlite.org/fileformat2.html: leaf table pages
0x0D, varints, record format, overflow chains). A page whose header or cells do not parse,
or holds a cell the caller rejects, is searched byte by byte for cells, so a damaged page
header or cell pointer loses no intact cell. Rows are returned as found, stale copies
(freed pages, older WAL frames) included: telling them apart is the caller's business.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Callable, NamedTuple

__all__ = ["Cell", "scan"]

_LEAF, _INTERIOR, _INDEX_LEAF, _INDEX_INTERIOR = 0x0D, 0x05, 0x0A, 0x02
_WAL_MAGIC = (0x377F0682, 0x377F0683)


class Cell(NamedTuple):
    """A table row found in the file: its page (``wal``: a page image of the -wal), rowid and values."""

    page: int
    wal: bool
    rowid: int
    values: tuple


def _varint(b: bytes, i: int, end: int) -> tuple[int, int]:
    """(value, next offset) of the SQLite varint at ``b[i]``; IndexError past ``end``."""
    v = 0
    for k in range(8):
        if i + k >= end:
            raise IndexError("varint past the end")
        c = b[i + k]
        v = (v << 7) | (c & 0x7F)
        if c < 0x80:
            return v, i + k + 1
    if i + 8 >= end:
        raise IndexError("varint past the end")
    return (v << 8) | b[i + 8], i + 9


_INT_SIZES = {1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 8}


def _record(p: bytes) -> tuple | None:
    """The values of a record (its whole payload ``p``), or None if it is not a well-formed record."""
    try:
        hsize, i = _varint(p, 0, len(p))
        if hsize < 1 or hsize > len(p):
            return None
        types = []
        while i < hsize:
            t, i = _varint(p, i, hsize)
            types.append(t)
        if i != hsize:
            return None
        out, j = [], hsize
        for t in types:
            if t == 0:
                out.append(None)
            elif t in _INT_SIZES:
                n = _INT_SIZES[t]
                if j + n > len(p):
                    return None
                out.append(int.from_bytes(p[j:j + n], "big", signed=True))
                j += n
            elif t == 7:
                if j + 8 > len(p):
                    return None
                out.append(struct.unpack(">d", p[j:j + 8])[0])
                j += 8
            elif t in (8, 9):
                out.append(t - 8)
            elif t >= 12:
                n = (t - 12) // 2
                if j + n > len(p):
                    return None
                out.append(bytes(p[j:j + n]))          # text and blobs alike: the caller decodes
                j += n
            else:
                return None
        return tuple(out) if j == len(p) else None
    except IndexError:
        return None


class _File:
    """The pages of a database file and of its -wal (page images, later frames last)."""

    def __init__(self, path: Path):
        self.data = path.read_bytes()
        self.size = self._page_size()
        self.usable = self.size - (self.data[20] if len(self.data) > 20 and self.data[20] < 64 else 0)
        self.pages = {k + 1: self.data[k * self.size:(k + 1) * self.size] for k in range(len(self.data) // self.size)}
        self.wal: list[tuple[int, bytes]] = []
        wal = Path(str(path) + "-wal")
        if wal.is_file():
            self._read_wal(wal.read_bytes())

    def _page_size(self) -> int:
        d = self.data
        if len(d) >= 100 and d[:16] == b"SQLite format 3\x00":
            s = int.from_bytes(d[16:18], "big")
            s = 65536 if s == 1 else s
            if 512 <= s <= 65536 and s & (s - 1) == 0 and len(d) % s == 0:
                return s
        # a damaged header: the smallest size at which nearly as many pages as at any size are b-tree pages
        share = {}
        for s in (512 << k for k in range(8)):
            if len(d) >= s and len(d) % s == 0:
                share[s] = sum(_btree_ok(d[o:o + s], 100 if o == 0 else 0) for o in range(0, len(d), s)) / (len(d) // s)
        best = max(share.values(), default=0.0)
        return min((s for s, v in share.items() if v >= 0.8 * best and v > 0), default=4096)

    def _read_wal(self, w: bytes) -> None:
        if len(w) < 32 or int.from_bytes(w[:4], "big") not in _WAL_MAGIC:
            return
        size = int.from_bytes(w[8:12], "big") or self.size
        size = 65536 if size == 1 else size
        if size != self.size:
            return
        o = 32
        while o + 24 + size <= len(w):
            pgno = int.from_bytes(w[o:o + 4], "big")
            if pgno:
                self.wal.append((pgno, w[o + 24:o + 24 + size]))
            o += 24 + size

    def overflow(self, first: int, need: int) -> bytes | None:
        """``need`` bytes of payload from the overflow chain starting at page ``first``."""
        out, seen, pg = bytearray(), set(), first
        while len(out) < need:
            if pg in seen or pg not in self.pages:
                return None
            seen.add(pg)
            page = self.pages[pg]
            out += page[4:self.usable][:need - len(out)]
            pg = int.from_bytes(page[:4], "big")
        return bytes(out)


def _btree_ok(page: bytes, hdr: int) -> bool:
    """Whether ``page`` looks like a b-tree page of its length: a b-tree type, its cell pointers inside it."""
    if len(page) < hdr + 12 or page[hdr] not in (_LEAF, _INTERIOR, _INDEX_LEAF, _INDEX_INTERIOR):
        return False
    first = hdr + (8 if page[hdr] in (_LEAF, _INDEX_LEAF) else 12)
    n = int.from_bytes(page[hdr + 3:hdr + 5], "big")
    if first + 2 * n > len(page):
        return False
    return all(first + 2 * n <= int.from_bytes(page[first + 2 * k:first + 2 * k + 2], "big") < len(page)
               for k in range(n))


def _local(f: _File, total: int) -> int:
    """Bytes of a table-leaf payload of ``total`` bytes stored on its page (the rest overflows)."""
    u = f.usable
    x, m = u - 35, ((u - 12) * 32 // 255) - 23
    if total <= x:
        return total
    k = m + (total - m) % (u - 4)
    return k if k <= x else m


def _cell(f: _File, page: bytes, o: int, end: int, allow_overflow: bool) -> tuple[int, tuple, int] | None:
    """(rowid, values, bytes the cell takes on its page) of the table-leaf cell at offset ``o``, or None."""
    try:
        total, i = _varint(page, o, end)
        rowid, i = _varint(page, i, end)
    except IndexError:
        return None
    if total < 2 or total > (1 << 30):
        return None
    local = _local(f, total)
    if local < total and not allow_overflow:
        return None
    if i + local > end:
        return None
    payload = page[i:i + local]
    if local < total:
        if i + local + 4 > end:
            return None
        more = f.overflow(int.from_bytes(page[i + local:i + local + 4], "big"), total - local)
        if more is None:
            return None
        payload = bytes(payload) + more
    values = _record(payload)
    if values is None:
        return None
    return rowid - (1 << 64) if rowid >= 1 << 63 else rowid, values, i + local + (4 if local < total else 0) - o


def _free_bytes(page: bytes, hdr: int, end: int) -> int | None:
    """Bytes of the page's freeblock chain and fragments; None if the chain is not well formed."""
    total, o, seen = page[hdr + 7], int.from_bytes(page[hdr + 1:hdr + 3], "big"), 0
    while o:
        if o + 4 > end or seen > end // 4:
            return None
        size = int.from_bytes(page[o + 2:o + 4], "big")
        total += size
        o, seen = int.from_bytes(page[o:o + 2], "big"), seen + 1
    return total


def _interior_ok(f: _File, page: bytes, hdr: int) -> bool:
    """Whether a table interior page's cells (child page, key), freeblocks and fragments fill its
    cell content area exactly."""
    n = int.from_bytes(page[hdr + 3:hdr + 5], "big")
    if hdr + 12 + 2 * n > f.usable:
        return False
    used = 0
    for k in range(n):
        o = int.from_bytes(page[hdr + 12 + 2 * k:hdr + 14 + 2 * k], "big")
        if not hdr + 12 + 2 * n <= o < f.usable - 4:
            return False
        try:
            used += _varint(page, o + 4, f.usable)[1] - o
        except IndexError:
            return False
    start = int.from_bytes(page[hdr + 5:hdr + 7], "big") or 65536
    free = _free_bytes(page, hdr, f.usable)
    return free is not None and used + free == f.usable - start


def _parse(f: _File, page: bytes, hdr: int) -> tuple[list[tuple[int, tuple]], bool]:
    """(cells, clean) of a page read through its header and cell pointers. Clean: every cell
    parsed, and cells, freeblocks and fragments fill the cell content area exactly (a damaged
    cell count or pointer leaves bytes unaccounted for)."""
    if len(page) < hdr + 8:
        return [], False
    kind = page[hdr]
    if kind in (_INDEX_LEAF, _INDEX_INTERIOR):
        return [], True                       # no table rows on it
    if kind == _INTERIOR:                     # no rows either, if it is one (a leaf's 0x0D is one bit away)
        return [], _interior_ok(f, page, hdr)
    if kind != _LEAF:
        return [], False
    n = int.from_bytes(page[hdr + 3:hdr + 5], "big")
    if hdr + 8 + 2 * n > f.usable:
        return [], False
    cells, clean, used = [], True, 0
    for k in range(n):
        o = int.from_bytes(page[hdr + 8 + 2 * k:hdr + 10 + 2 * k], "big")
        got = _cell(f, page, o, f.usable, True) if hdr + 8 + 2 * n <= o < f.usable else None
        if got is None:
            clean = False
        else:
            cells.append(got[:2])
            used += got[2]
    start = int.from_bytes(page[hdr + 5:hdr + 7], "big") or 65536
    free = _free_bytes(page, hdr, f.usable)
    if free is None or used + free != f.usable - start:
        clean = False
    return cells, clean


def _search(f: _File, page: bytes, hdr: int) -> list[tuple[int, tuple]]:
    """Every well-formed table-leaf cell (no overflow) at any offset of a page."""
    out, end = [], f.usable
    for o in range(hdr + 8, end - 3):
        c = page[o]
        if c == 0:                           # a payload of 0 bytes is no row: skip zero runs quickly
            continue
        got = _cell(f, page, o, end, False)
        if got is not None and got[1]:
            out.append(got[:2])
    return out


def scan(path: str | Path, judge: Callable[[int, tuple], bool | None] = lambda rowid, values: None) -> list[Cell]:
    """Every table row found in the pages of the database file ``path`` and of its -wal.

    ``judge(rowid, values)``: True for a row the caller knows to be whole, False for one it
    knows to be damaged, None for a row it does not recognise. A page that does not parse, or
    that holds a row judged False, is also searched byte by byte.
    """
    f = _File(Path(path))
    out: list[Cell] = []
    images = [(k, False, p) for k, p in f.pages.items()] + [(k, True, p) for k, p in f.wal]
    for pgno, wal, page in images:
        hdr = 100 if pgno == 1 else 0
        cells, clean = _parse(f, page, hdr)
        if clean and all(judge(r, v) is not False for r, v in cells):
            found = cells
        else:
            seen = set(cells)
            found = cells + [c for c in _search(f, page, hdr) if c not in seen]
        out.extend(Cell(pgno, wal, r, v) for r, v in found)
    return out
