"""Tables for the terminal that never cut a value.

rich shrinks a table that is wider than the terminal by cutting its cells (``0.5499…``); a
number cut short is a wrong number. :func:`print_table` instead lets headers wrap at their
spaces, keeps every value whole, and where the columns still do not fit the terminal's width
prints them as several tables one under the other, each repeating the first (key) column, the
way a printed table continues on the next page.
"""

from __future__ import annotations

from rich import box
from rich.table import Table

__all__ = ["print_table", "table_width"]


def _widths(header: str, values) -> int:
    """A column's width: its widest value, and its header's longest word (headers wrap)."""
    return max([len(v) for v in values] + [max((len(w) for w in header.split()), default=0)])


def table_width(widths) -> int:
    """The width rich gives a SIMPLE_HEAD table of columns of these content widths (padding 1
    each side and one separator between and around columns)."""
    return sum(widths) + 3 * len(widths) + 1


def _groups(widths: list[int], limit: int) -> list[list[int]]:
    """Column indices (after the key column 0) split greedily into tables that fit ``limit``."""
    groups, current = [], []
    for i in range(1, len(widths)):
        if current and table_width([widths[0]] + [widths[j] for j in current + [i]]) > limit:
            groups.append(current)
            current = []
        current.append(i)
    if current or not groups:
        groups.append(current)
    return groups


def print_table(console, columns, rows, *, title=None, caption=None) -> None:
    """Print ``rows`` (lists of str) under ``columns`` (``(header, justify)`` pairs).

    Values are never wrapped or cut: a table wider than ``console.width`` is continued below,
    with the first column repeated.
    """
    widths = [_widths(h, [r[i] for r in rows]) for i, (h, _) in enumerate(columns)]
    full = [max(w, len(h)) for w, (h, _) in zip(widths, columns)]      # headers on one line
    groups = _groups(widths, console.width)
    for k, group in enumerate(groups):
        cols = [0] + group
        if table_width([full[i] for i in cols]) <= console.width:
            cols_width = {i: full[i] for i in cols}
        else:
            cols_width = {i: widths[i] for i in cols}
        t = Table(title=(title if k == 0 else f"{title} (continued)") if title else None, box=box.SIMPLE_HEAD,
                  caption=caption if k == len(groups) - 1 else None, expand=False)
        # a lone column still wider than the terminal (prose, such as the fit's flags) wraps
        # at its spaces; the key column stays whole
        too_wide = table_width([cols_width[i] for i in cols]) > console.width
        for i in cols:
            header, justify = columns[i]
            if too_wide and i != 0:
                t.add_column(header, justify=justify, overflow="fold")
            else:
                t.add_column(header, justify=justify, width=cols_width[i], overflow="fold", no_wrap=too_wide)
        for r in rows:
            t.add_row(*[r[i] for i in cols])
        console.print(t)
