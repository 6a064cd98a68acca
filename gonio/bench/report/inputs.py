"""What the report reads, read as hostile: inside the output folder only, typed, bounded.

Every file the report opens (the files it finds and the files they name) must resolve,
symlinks followed, to a regular file inside the output folder given to ``gonio report``;
anything else is refused with a :class:`GonioError` (one line, exit status 2) before the
report writes anything. A reference with ``..`` is refused; an absolute one is accepted only
when it resolves inside the folder (``gonio render`` writes absolute names today); a relative
one is taken from the naming file's folder (or, for files written by an older ``gonio
render`` with a relative ``--out``, from the working folder) and must resolve inside too. A
reference that no longer leads into the folder (the folder was moved or copied after ``gonio
render`` wrote it) is taken from the file of the same name beside the naming file, when there is one.

JSON values are read through :class:`Doc`: a field where a number belongs must be a number
(NaN and inf are numbers; strings, lists, booleans are refused, naming the field), text is
cut to a bounded length, and every value goes to HTML only through the template's escaping.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path, PurePath

from gonio.core.errors import GonioError

__all__ = ["Doc", "Folder", "show"]

MAX_JSON_BYTES = 64 << 20
MAX_IMAGE_BYTES = 32 << 20
MAX_TEXT = 400
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def show(value, limit: int = 48) -> str:
    """A short, printable (ASCII) rendering of a hostile value for a one-line message."""
    text = ascii(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class Folder:
    """The output folder the report may read; paths are checked against its real path."""

    def __init__(self, folder):
        self.path = Path(folder)
        if not self.path.is_dir():
            raise GonioError(f"{self.path} is not a folder; give the output folder of `gonio demo` or a session folder")
        self.real = Path(os.path.realpath(self.path))

    def label(self, path) -> str:
        """``path`` relative to the folder, for messages."""
        try:
            return str(Path(path).relative_to(self.path))
        except ValueError:
            return str(path)

    def _inside(self, real: str) -> bool:
        root = str(self.real)
        return real == root or real.startswith(root.rstrip(os.sep) + os.sep)

    def check(self, path, what: str) -> Path:
        """The real path of ``path`` when it is a regular file inside the folder; else refuse."""
        real = os.path.realpath(path)
        if not self._inside(real):
            raise GonioError(f"{what} {self.label(path)} resolves to {show(real, 120)}, outside {self.path}; "
                             "the report reads only files inside the output folder: copy the file in instead of linking it")
        try:
            st = os.stat(real)
        except OSError as exc:
            raise GonioError(f"{what} {self.label(path)} cannot be read ({exc.strerror})") from None
        if not stat.S_ISREG(st.st_mode):
            raise GonioError(f"{what} {self.label(path)} is not a regular file")
        return Path(real)

    def read_bytes(self, path, what: str, limit: int) -> bytes:
        """The bytes of a checked file, opened without following a link swapped in after the check."""
        real = self.check(path, what)
        try:
            fd = os.open(real, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        except OSError as exc:
            raise GonioError(f"{what} {self.label(path)} cannot be read ({exc.strerror})") from None
        try:
            st = os.fstat(fd)
            proc = f"/proc/self/fd/{fd}"
            if not stat.S_ISREG(st.st_mode) or (os.path.exists(proc) and not self._inside(os.path.realpath(proc))):
                raise GonioError(f"{what} {self.label(path)} changed while it was read; run the report again")
            if st.st_size > limit:
                raise GonioError(f"{what} {self.label(path)} is {st.st_size >> 20} MiB, more than the report reads "
                                 f"({limit >> 20} MiB); it is not a file gonio wrote")
            with os.fdopen(fd, "rb") as fh:
                fd = -1
                data = fh.read(limit + 1)
        finally:
            if fd >= 0:
                os.close(fd)
        return data

    def reference(self, value, named_in: Path, key: str, *, fix: str):
        """The checked real path a JSON file names under ``key``; None when the file is missing.

        A reference that is not a string, holds ``..``, or resolves outside the folder is
        refused; one inside the folder that no longer exists is None (the caller says so).
        """
        where = f"{self.label(named_in)}: {key}"
        if not isinstance(value, str) or not value.strip() or "\x00" in value or len(value) > 4096:
            raise GonioError(f"{where} must name a file inside {self.path}, not {show(value)}; {fix}")
        ref = PurePath(value)
        if ".." in ref.parts:
            raise GonioError(f"{where} = {show(value)} climbs out with '..'; the report reads only files inside "
                             f"{self.path}: {fix}")
        if ref.is_absolute():
            candidates = [Path(ref)]
        else:
            candidates = [Path(named_in).parent / ref, Path.cwd() / ref]
        # a folder moved or copied after the file was written: its reference (absolute, or relative
        # to the folder `gonio render` ran in) names the old place; the file lies beside the naming one
        beside = Path(named_in).parent / ref.name
        chosen = next((c for c in candidates if os.path.lexists(c) and self._inside(os.path.realpath(c))), None)
        if chosen is None and ref.name and os.path.lexists(beside):
            chosen = beside
        if chosen is None:
            chosen = next((c for c in candidates if os.path.lexists(c)), None)
        if chosen is None:
            return None
        if not self._inside(os.path.realpath(chosen)):
            raise GonioError(f"{where} = {show(value)} points outside {self.path} (to {show(os.path.realpath(chosen), 120)}); "
                             f"the report embeds only files inside the output folder: {fix}")
        return self.check(chosen, key)

    def read_json(self, path, what: str, *, fix: str, strict: bool = False) -> "Doc":
        """A JSON object from a file inside the folder, as a :class:`Doc`; refuse anything else.

        ``strict``: refuse NaN and Infinity, which are not JSON (a fit file never holds them).
        """
        label = self.label(path)
        data = self.read_bytes(path, what, MAX_JSON_BYTES)

        def constant(name):
            raise GonioError(f"{label} holds {name}, which is not JSON (a gonio fit file writes null); {fix}")

        try:
            doc = json.loads(data.decode("utf-8"), **({"parse_constant": constant} if strict else {}))
        except UnicodeDecodeError:
            raise GonioError(f"{label} is not UTF-8 text; {fix}") from None
        except RecursionError:
            raise GonioError(f"{label} is nested too deeply to be a gonio file; {fix}") from None
        except ValueError as exc:  # JSONDecodeError, or an integer longer than Python converts
            raise GonioError(f"{label} is not valid JSON ({' '.join(str(exc).split())[:120]}); {fix}") from None
        if not isinstance(doc, dict):
            raise GonioError(f"{label} must hold a JSON object, not {type(doc).__name__}; {fix}")
        return Doc(doc, label, fix=fix)


class Doc:
    """Typed, bounded access to a JSON object read from ``label``; wrong types are refused."""

    def __init__(self, data: dict, label: str, where: str = "", *, fix: str):
        self.data, self.label, self.where, self.fix = data, label, where, fix

    def _name(self, key) -> str:
        return f"{self.where}.{key}" if self.where else str(key)

    def refuse(self, key, what: str, value=None):
        raise GonioError(f"{self.label}: {self._name(key)} must be {what}, not {show(value)}; "
                         f"the file is damaged or not written by gonio: {self.fix}")

    def raw(self, key, default=None):
        return self.data.get(key, default)

    def has(self, key) -> bool:
        return self.data.get(key) is not None

    def sub(self, key) -> "Doc | None":
        """The object under ``key`` (None when absent or null)."""
        v = self.data.get(key)
        if v is None:
            return None
        if not isinstance(v, dict):
            self.refuse(key, "an object", v)
        return Doc(v, self.label, self._name(key), fix=self.fix)

    def need(self, key) -> "Doc":
        d = self.sub(key)
        if d is None:
            self.refuse(key, "an object", None)
        return d

    def rows(self, key, limit: int = 10_000) -> "list[Doc]":
        """The list of objects under ``key`` ([] when absent or null)."""
        v = self.data.get(key)
        if v is None:
            return []
        if not isinstance(v, list) or len(v) > limit:
            self.refuse(key, f"a list of at most {limit} objects", v)
        out = []
        for i, item in enumerate(v):
            if not isinstance(item, dict):
                self.refuse(f"{key}[{i}]", "an object", item)
            out.append(Doc(item, self.label, f"{self._name(key)}[{i}]", fix=self.fix))
        return out

    def items(self, key) -> "list[tuple[str, Doc]]":
        """The (name, object) pairs of the object under ``key``."""
        d = self.sub(key)
        if d is None:
            return []
        out = []
        for k, v in d.data.items():
            if not isinstance(v, dict):
                d.refuse(k, "an object", v)
            out.append((k, Doc(v, self.label, d._name(k), fix=self.fix)))
        return out

    def num(self, key, *, required: bool = False):
        """A number (int or float, NaN and inf included) or None when absent or null."""
        v = self.data.get(key)
        if v is None:
            if required:
                self.refuse(key, "a number", v)
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.refuse(key, "a number", v)
        if isinstance(v, int) and abs(v) > 2 ** 63:
            self.refuse(key, "a number of sensible size", v)
        return v

    def count(self, key, *, required: bool = False):
        """A non-negative whole number (a count or an index) or None."""
        v = self.num(key, required=required)
        if v is None:
            return None
        if (isinstance(v, float) and not (math.isfinite(v) and v.is_integer())) or v < 0:
            self.refuse(key, "a whole number >= 0", v)
        return int(v)

    def text(self, key, *, required: bool = False, limit: int = MAX_TEXT):
        """A string (numbers are written out) cut to ``limit`` characters, or None."""
        v = self.data.get(key)
        if v is None:
            if required:
                self.refuse(key, "a string", v)
            return None
        if isinstance(v, bool) or not isinstance(v, (str, int, float)):
            self.refuse(key, "a string", v)
        return cut(str(v), limit)

    def flag(self, key) -> bool:
        v = self.data.get(key)
        if v is None:
            return False
        if not isinstance(v, bool) and v not in (0, 1):
            self.refuse(key, "true or false", v)
        return bool(v)

    def numbers(self, key, *, length: int | None = None):
        """A list of numbers (or None): ``ci90`` and the like."""
        v = self.data.get(key)
        if v is None:
            return None
        if not isinstance(v, list) or (length is not None and len(v) != length) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            self.refuse(key, f"a list of {length or 'some'} numbers", v)
        return v

    def json_text(self, key, limit: int = MAX_TEXT) -> str:
        """Any JSON value under ``key`` written as compact JSON text, cut to ``limit``."""
        try:
            return cut(json.dumps(self.data.get(key, {})), limit)
        except (ValueError, TypeError, RecursionError):
            self.refuse(key, "plain JSON", self.data.get(key))


def cut(text: str, limit: int = MAX_TEXT) -> str:
    """``text`` cut to ``limit`` characters (saying how long it was), with control and
    format characters (terminal escapes, bidi overrides) written as visible escapes."""
    text = str(text)
    short = text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters, cut)"
    if short.isprintable():
        return short
    return "".join(ch if ch.isprintable() or ch in "\n\t" else ascii(ch)[1:-1] for ch in short)
