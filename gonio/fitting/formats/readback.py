"""Every exchange-format writer checks what it wrote before the file gets its name.

A writer writes into temporaries (:func:`gonio.core.atomic.atomic_path`), reads them back (or
counts what they hold), compares with what it was given and only then renames them:
:func:`written` does this for one file or a set of files, so a mismatch leaves no file (and
an earlier file of the same name as it was). :class:`ExportError` is the project's one-line
error (exit status 2 at the command line).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from gonio.core.atomic import atomic_path
from gonio.core.errors import GonioError

__all__ = ["ExportError", "written", "expect"]


class ExportError(GonioError):
    """An exported file does not hold what its writer had: nothing was written."""


def expect(what: str, had, wrote) -> None:
    """Raise :class:`ExportError` unless ``wrote == had`` (``what`` names the counted thing)."""
    if had != wrote:
        raise ExportError(f"export check failed: {what}: had {had}, the file holds {wrote}; nothing was written")


def written(writers: dict, check) -> list[Path]:
    """Write files all or nothing, checked before they are renamed.

    Parameters
    ----------
    writers : dict
        ``{path: write(tmp_path)}``: each callable writes its file under the temporary name
        it is given.
    check : callable
        ``check({path: tmp_path})`` reads the temporaries back and raises
        :class:`ExportError` (:func:`expect`) where they differ from what was meant.

    Returns
    -------
    list of Path
        The paths written, in ``writers``' order.
    """
    with contextlib.ExitStack() as stack:
        tmps = {}
        for path, write in writers.items():
            tmp = stack.enter_context(atomic_path(path, keep_suffix=True))
            write(tmp)
            tmps[Path(path)] = Path(tmp)
        check(tmps)
    return [Path(p) for p in writers]
