"""An HDF5/NetCDF-4 file walked whole in a child process with a deadline, before gonio reads it.

A damaged file can send the HDF5 library into a loop that never returns (one zeroed 512-byte
block inside a dataset.nc did, in `gonio fit` and `gonio report`), and no Python signal reaches
it. :func:`check_hdf5` reads every group, attribute and variable of the file in a child that
imports h5py alone, and says in one line (GonioError) when the child fails or runs past its
deadline; only then does the caller read the file itself, with the same library.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from gonio.core.errors import GonioError

__all__ = ["check_hdf5", "DEADLINE_S"]

#: seconds the walk may take, plus one second a 10 MB (a dataset.nc of 1e5 points reads in ~0.1 s)
DEADLINE_S = 20.0

_WALK = """
import sys
import h5py

def visit(obj):
    for key in obj.attrs:
        obj.attrs[key]
    if isinstance(obj, h5py.Dataset):
        obj[()]
    elif isinstance(obj, h5py.Group):
        for name in obj:
            visit(obj[name])

with h5py.File(sys.argv[1], "r") as f:
    visit(f)
"""


def check_hdf5(path, what: str = "dataset") -> None:
    """Read all of ``path`` (HDF5 / NetCDF-4) in a child process; GonioError (one line) if it
    cannot be read whole within :data:`DEADLINE_S` (plus a second per 10 MB)."""
    path = Path(path)
    deadline = DEADLINE_S + os.path.getsize(path) / 10e6
    try:
        r = subprocess.run([sys.executable, "-I", "-c", _WALK, os.fspath(path)], capture_output=True,
                           timeout=deadline)
    except subprocess.TimeoutExpired:
        raise GonioError(f"{what} {path} is damaged: reading its structure did not finish in {deadline:.0f} s; "
                         "export it again from its session or restore a copy") from None
    if r.returncode != 0:
        last = (r.stderr.decode("utf-8", "replace").strip().splitlines() or ["no message"])[-1]
        if "filter returned failure" in last:       # HDF5's Fletcher-32 check of a stored block
            raise GonioError(f"{what} {path} is damaged: a stored block fails its checksum; export it again "
                             "from its session (gonio verify SESSION checks the journal) or restore a copy") from None
        raise GonioError(f"cannot read {what} {path} ({' '.join(last.split())[:200]}); "
                         "give a dataset.nc written by gonio export") from None
