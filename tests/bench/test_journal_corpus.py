"""A corpus of damaged journals (issue 36): one bit flipped in each page of a finished session's
journal.sqlite in turn. Whatever the page: no traceback; what an export or a resume reads is
either refused in one line or exactly what was measured; `verify` and `--rebuild-journal`
recover every point whose row does not hold the flipped byte (at most one does).

In the suite: every page once (a byte of its cell content on even pages; its type byte, cell
count or first cell pointer on odd ones) and the file header's magic and page size. Marked
``long`` (`pytest -m long`): every page at 11 offsets with three different bits each.
"""

import os
import shutil
import time

import pytest

pytest.importorskip("gonio.sim")

from gonio.bench.samples import load_sample
from gonio.bench.session import integrity
from gonio.bench.session.journal import Journal
from gonio.bench.session.verify import verify_session
from gonio.cli.capture import capture_sim
from gonio.core.errors import SessionError

_ROW_OVERHEAD = 9 * 8 + 40          # 9 numbers, the record header and the cell's own varints, at most


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    """A finished quick session, its journal's bytes and page size, and each point's byte span."""
    root = tmp_path_factory.mktemp("corpus")
    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=1, progress=False)
    folder = root / "session"
    with Journal(folder / "journal.sqlite") as j:
        rows = {r["idx"]: r for r in j.points()}
        sums = dict(j.db.execute("SELECT idx, checksum FROM points"))
        texts = {k: j.db.execute("SELECT length(brdf) + length(brdf_std) + length(detail) FROM points WHERE idx = ?",
                                 (k,)).fetchone()[0] for k in rows}
        size = j.db.execute("PRAGMA page_size").fetchone()[0]
    data = (folder / "journal.sqlite").read_bytes()
    assert not os.path.exists(folder / "journal.sqlite-wal") or os.path.getsize(folder / "journal.sqlite-wal") == 0
    spans = {}
    for k, s in sums.items():            # the checksum is the last column: the row ends with it
        end = data.find(s.encode()) + len(s)
        assert end > len(s) and data.find(s.encode(), end) < 0
        spans[k] = (end - len(s) - texts[k] - _ROW_OVERHEAD, end)
    return {"folder": folder, "rows": rows, "data": data, "size": size, "spans": spans}


def _case(original, tmp_path, at, bit):
    """Flip ``bit`` of byte ``at`` and check every reader; returns the rebuild's line (or refusal)."""
    src = original["folder"]
    folder = tmp_path / f"c{at}_{bit}"
    folder.mkdir()
    os.symlink(src / "raw", folder / "raw")            # RAW files are only read
    shutil.copyfile(src / "session.toml", folder / "session.toml")
    data = bytearray(original["data"])
    data[at] ^= bit
    (folder / "journal.sqlite").write_bytes(bytes(data))
    rows = original["rows"]
    hit = {k for k, (a, b) in original["spans"].items() if a <= at < b}
    assert len(hit) <= 2
    text, doc, why = integrity.load_session(folder)
    try:                                  # what export and resume read: refused, or exactly what was measured
        with integrity.open_journal(folder, text, doc, why, write=False) as j:
            got = j.points()
            j.events()                    # export reads the events too (instrument time, open beam)
        assert got == [rows[k] for k in sorted(rows)], f"byte {at}: a damaged journal read as whole"
        refused = False
    except SessionError as exc:
        assert "\n" not in str(exc)
        refused = True
    verdict = verify_session(folder)
    assert verdict.ok is not refused, (at, verdict.lines())
    assert set(range(len(rows))) - set(verdict.intact) <= hit, (at, verdict.lines())
    try:
        line = integrity.rebuild_journal(folder, text, doc, why)
    except SessionError as exc:
        assert not refused and "nothing to rebuild" in str(exc), (at, str(exc))
        return "whole"
    with Journal(folder / "journal.sqlite") as j:
        kept = {r["idx"]: r for r in j.points()}
    assert all(kept[k] == rows[k] for k in kept), f"byte {at}: a rebuilt point differs from what was measured"
    lost = set(rows) - set(kept)
    assert lost <= hit and len(lost) <= 1, (at, lost, hit, line)
    return line


def _offsets(size, pages, every):
    """Byte offsets to flip: (page, offset class) pairs as the module docstring says."""
    out = []
    for p in range(pages):
        base, hdr = p * size, 100 if p == 0 else 0
        header = [hdr, hdr + 3, hdr + 4, hdr + 8, hdr + 9]                # type, cell count, first pointer
        content = [size - 1 - ((p * 389 + 97 * k) % (size - hdr - 16)) for k in range(6)]
        if every:
            out += [base + o for o in header + content]
        else:
            out.append(base + (content[0] if p % 2 == 0 else header[(p // 2) % len(header)]))
    return out


def test_one_flip_in_every_page(original, tmp_path):
    size = original["size"]
    pages = len(original["data"]) // size
    offsets = [0, 16] + _offsets(size, pages, every=False)
    t0 = time.perf_counter()
    lines = [_case(original, tmp_path, at, 0x08) for at in offsets]   # 0x08: a leaf page (0x0D) reads as interior
    assert pages >= 40 and len(lines) == pages + 2
    assert sum(line.startswith("rebuilt the journal: 30 point(s)") for line in lines) >= pages // 2
    assert time.perf_counter() - t0 < 120


@pytest.mark.long
@pytest.mark.parametrize("bit", [0x01, 0x08, 0x80])
def test_many_flips_in_every_page(original, tmp_path, bit):
    size = original["size"]
    offsets = list(range(0, 100, 7)) + _offsets(size, len(original["data"]) // size, every=True)
    for at in offsets:
        _case(original, tmp_path, at, bit)
