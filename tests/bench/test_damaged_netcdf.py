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


def _read_or_refuse(dataset, tmp_path, step):
    """For each ``step``-aligned zeroed 512-byte block: "refused" (one line) or "same" (read back
    equal to the intact file); anything else is a damaged file read as if it were good."""
    import numpy as np

    from gonio.bench.dataset.reader import open_dataset

    intact = open_dataset(dataset)
    out = {"refused": 0, "same": 0, "different": []}
    for offset in range(0, os.path.getsize(dataset), step):
        path = _zeroed(dataset, tmp_path / f"r{offset}.nc", offset)
        try:
            meas = open_dataset(path)
        except GonioError as exc:
            assert "\n" not in str(exc)
            out["refused"] += 1
        else:
            same = all(np.array_equal(getattr(meas, k), getattr(intact, k), equal_nan=True)
                       for k in ("wi", "wo", "brdf", "brdf_std", "use"))
            if same:
                out["same"] += 1
            else:
                out["different"].append(offset)
        path.unlink()
    return out


def _chunk_offset(path, name):
    """File offset and size of the first stored chunk of variable ``name`` (contiguous: its data)."""
    import h5py

    with h5py.File(path, "r") as f:
        dsid = f[name].id
        if f[name].chunks is None:
            return dsid.get_offset(), dsid.get_storage_size()
        info = dsid.get_chunk_info(0)
        return info.byte_offset, info.size


@pytest.mark.parametrize("name", ["brdf", "brdf_std", "theta_o"])
def test_a_flipped_bit_in_stored_values_is_refused(dataset, tmp_path, name):
    """Every array of dataset.nc is stored with HDF5's Fletcher-32 checksum (export): one flipped
    bit in a stored f_r, sigma or angle is refused when read. Before, it was read as a value
    (issue 36, probe 3: 0.248 -> 0.348 exported and fitted without a word)."""
    from gonio.bench.dataset.reader import open_dataset

    offset, size = _chunk_offset(dataset, name)
    path = tmp_path / "flipped.nc"
    shutil.copy(dataset, path)
    with open(path, "r+b") as fh:
        fh.seek(offset + size // 2)
        byte = fh.read(1)[0]
        fh.seek(offset + size // 2)
        fh.write(bytes([byte ^ 0x10]))
    with pytest.raises(GonioError, match="fails its checksum") as info:
        open_dataset(path)
    assert "\n" not in str(info.value)


@pytest.mark.long
def test_no_zeroed_block_anywhere_is_read_as_good_data(dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(hc, "DEADLINE_S", 3.0)
    out = _read_or_refuse(dataset, tmp_path, 512)
    assert out["different"] == [], f"read as good data with blocks zeroed at {out['different']}"
