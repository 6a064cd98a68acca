"""A damaged dataset.nc is an error within seconds, never a hang (issue 36, probe 4).

One zeroed 512-byte block inside a dataset.nc made `gonio fit` and `gonio report` spin at
100 % CPU for ever: the HDF5 library loops in C, where no Python signal reaches it. The file is
now walked whole in a child process with a deadline first (gonio.core.hdf5check). On a quick
capture's dataset (73 kB) zeroing each 2 kB-aligned block in turn: 4 of 36 hung before (in
h5py 3 as pinned), 26 others were refused by HDF5's own checks, 6 read (data blocks).
"""

import os
import shutil
import threading

import pytest

import gonio.core.hdf5check as hc
from gonio.core.errors import GonioError


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.bench.session.simulated import capture_sim

    root = tmp_path_factory.mktemp("damaged")
    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=1, progress=False)
    return export(root / "session")


def _zeroed(src, dst, offset):
    shutil.copy(src, dst)
    with open(dst, "r+b") as fh:
        fh.seek(offset)
        fh.write(b"\0" * 512)
    return dst


@pytest.mark.slow
def test_every_zeroed_block_is_an_answer_within_the_deadline(dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(hc, "DEADLINE_S", 3.0)
    hc.check_hdf5(dataset)                   # the intact file walks through
    hung, refused = [], []
    for offset in range(0, os.path.getsize(dataset), 2048):
        path = _zeroed(dataset, tmp_path / f"z{offset}.nc", offset)
        try:
            hc.check_hdf5(path)
        except GonioError as exc:
            (hung if "did not finish" in str(exc) else refused).append(offset)
            assert "\n" not in str(exc)
        path.unlink()
    # the files that loop HDF5 are among them (else this test would not test the deadline)
    assert hung, "no zeroed block made HDF5 loop: the deadline path was not exercised"
    assert refused


@pytest.mark.slow
def test_gonio_fit_on_a_file_that_loops_hdf5_exits_2(dataset, tmp_path, monkeypatch, capsys):
    """The CLI's answer on the first block that loops HDF5: one line, exit 2, within the deadline
    (run in a thread: on the code before the fix the call never returns)."""
    from gonio.cli.main import main

    monkeypatch.setattr(hc, "DEADLINE_S", 3.0)
    looping = None
    for offset in range(0, os.path.getsize(dataset), 2048):
        path = _zeroed(dataset, tmp_path / "d.nc", offset)
        try:
            hc.check_hdf5(path)
        except GonioError as exc:
            if "did not finish" in str(exc):
                looping = path
                break
    assert looping is not None
    out = {}

    def run():
        out["rc"] = main(["fit", str(looping), "--model", "diffuse", "--out", str(tmp_path / "f.json")])
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(60.0)
    assert not t.is_alive(), "gonio fit still ran after 60 s"
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert out["rc"] == 2 and len(err) == 1 and "is damaged" in err[0], err
    assert not (tmp_path / "f.json").exists()
