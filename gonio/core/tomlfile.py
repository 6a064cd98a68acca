"""TOML a user gives (settings, samples, plans, calibrations, fault schedules), read as
hostile: a regular file of at most :data:`MAX_BYTES`, UTF-8, parsed with limits (nesting
depth, integer size), so that a bad file is one line (GonioError), never a traceback, a hang
or an integer too large for the arithmetic that reads it."""

from __future__ import annotations

import sys
import tomllib

from gonio.core.errors import GonioError
from gonio.core.preflight import check_input_file

__all__ = ["read_toml", "parse_toml", "MAX_BYTES", "MAX_DEPTH", "MAX_INT"]

#: the largest TOML file any of gonio's inputs can plausibly be (a plan of 10^4 points is ~1 MB)
MAX_BYTES = 16 << 20
#: tables and arrays nested deeper than this are not a gonio input
MAX_DEPTH = 32
#: integers beyond int64 are not a gonio input (seeds, counts, indices, exposures)
MAX_INT = 2 ** 63 - 1


def _check(value, what: str, depth: int = 0) -> None:
    if depth > MAX_DEPTH:
        raise GonioError(f"{what} nests tables or arrays more than {MAX_DEPTH} deep; fix the file")
    if isinstance(value, dict):
        for v in value.values():
            _check(v, what, depth + 1)
    elif isinstance(value, list):
        for v in value:
            _check(v, what, depth + 1)
    elif isinstance(value, int) and not isinstance(value, bool) and abs(value) > MAX_INT:
        raise GonioError(f"{what} holds an integer of {len(str(abs(value)))} digits; no value may exceed 2**63 - 1")


def parse_toml(text: str, what: str) -> dict:
    """``text`` as TOML; GonioError (one line naming ``what``) for bad syntax, nesting or integers."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise GonioError(f"{what} is not valid TOML ({exc}); fix the syntax") from None
    except RecursionError:
        raise GonioError(f"{what} nests tables or arrays more than {MAX_DEPTH} deep; fix the file") from None
    except ValueError:                  # an integer beyond Python's digit limit (sys.int_info)
        raise GonioError(f"{what} holds an integer of more than {sys.get_int_max_str_digits()} digits; "
                         "no value may exceed 2**63 - 1") from None
    _check(doc, what)
    return doc


def read_toml(path, what: str) -> dict:
    """The TOML file ``path``, checked (:func:`parse_toml`): a regular file of at most
    :data:`MAX_BYTES`, UTF-8; GonioError (one line) otherwise."""
    path = check_input_file(path, what, max_bytes=MAX_BYTES)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise GonioError(f"cannot read {what} {path}: {exc.strerror}; check the path") from None
    except UnicodeDecodeError:
        raise GonioError(f"{what} {path} is not UTF-8 text; give a TOML file") from None
    return parse_toml(text, f"{what} {path}")
