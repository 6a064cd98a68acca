"""``gonio convert``: exchange formats (`gonio.bench.dataset.convert`). A fit -> Mitsuba XML (a
plain Mitsuba's, or with gonio's plugins) / dict JSON / MERL / PAB-Opto; a dataset -> CSV /
MERL (binned) / PAB-Opto."""

from __future__ import annotations

from pathlib import Path

from gonio.bench.dataset.convert import convert

__all__ = ["convert_cli"]


def convert_cli(source: Path, out: Path, to: str) -> None:
    """``gonio convert SOURCE --to FORMAT --out OUT``: the library's conversion, its lines printed."""
    convert(source, out, to, say=print)
