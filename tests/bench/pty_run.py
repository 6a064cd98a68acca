"""Run a command on a pseudo-terminal of a given size, as a person at a terminal would see it.

``run_in_pty(argv, cols=80)`` gives ``(exit status, everything written to the terminal)``: stdin,
stdout and stderr are the pty's slave side (so ``isatty()`` is true for all three), ``TERM`` is
xterm, ``COLUMNS``/``LINES`` and the window size say ``cols`` x ``rows``; ``FORCE_COLOR`` and
``TTY_COMPATIBLE`` are removed so that the program decides from the terminal alone.
"""

from __future__ import annotations

import fcntl
import os
import re
import select
import struct
import subprocess
import termios
import time

__all__ = ["run_in_pty", "frames", "strip_ansi"]


def run_in_pty(argv, *, cols: int = 80, rows: int = 24, timeout: float = 300.0, cwd=None, env=None):
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
    e = dict(os.environ, TERM="xterm-256color", COLUMNS=str(cols), LINES=str(rows))
    for name in ("FORCE_COLOR", "TTY_COMPATIBLE", "NO_COLOR"):
        e.pop(name, None)
    e.update(env or {})
    proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, cwd=cwd, env=e, close_fds=True,
                            start_new_session=True)
    os.close(slave)
    out = bytearray()
    deadline = time.monotonic() + timeout
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 0.1)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:             # EIO: the slave side closed (the process ended)
                    break
                if not chunk:
                    break
                out += chunk
            elif proc.poll() is not None:
                break
            if time.monotonic() > deadline:
                proc.kill()
                break
    finally:
        os.close(master)
    return proc.wait(timeout=30), out.decode("utf-8", "replace")


_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def strip_ansi(text: str) -> str:
    return _ANSI.sub("", text)


def frames(screen: str) -> list[str]:
    """Each line or redraw of a line (split at CR and LF), escape sequences removed."""
    return [strip_ansi(f) for f in re.split(r"[\r\n]", screen) if strip_ansi(f).strip()]
