"""Serve a simulated instrument's ports on pseudo-terminals (``gonio sim serve``).

Each port (``zaber``, ``meter``, ``camera``) gets a pty; the server keeps its own handle on
the slave side, so a client may close the port and open it again (a capture process that
crashes and restarts) without the server noticing. Stable paths: ``<link_dir>/<port>`` are
symlinks to the current ``/dev/pts/N``; the ``vanish`` fault closes a pty (the client sees
EIO / a hang-up), removes the link and, ``duration`` seconds later (wall time divided by the
clock scale; real seconds for an instant clock), re-creates it under a new ``/dev/pts/N``
with the link re-pointed, as udev does for a USB adapter that re-enumerates.
"""

# Each port is served by its own thread (its own ``select`` loop over its master), as each
# device on a real rig answers on its own: a meter that averages for seconds delays only its own
# replies, never the stage chain's. Bytes go through the same ``PortEndpoint`` as the ``sim://``
# transport, so replies are byte-identical. A port's loop sleeps no longer than until the next
# spontaneous line comes due (``PortEndpoint.next_due``: a motion's end, for its alert), so an
# alert leaves within a few milliseconds of the motion's end.

from __future__ import annotations

import os
import pty
import select
import tempfile
import threading
import time
import tty

from gonio.sim.physics.clock import SimClock
from gonio.sim.instrument import DEFAULT_REFERENCE, DEFAULT_SAMPLE, Instrument

__all__ = ["PtyServer", "serve"]


#: bytes a port keeps for a client that does not read (then the oldest whole lines go)
MAX_PENDING = 1 << 16


class PtyServer:
    """Pseudo-terminal server of one instrument.

    Parameters
    ----------
    instrument : Instrument
        The simulated instrument.
    link_dir : str or None
        Folder for the stable symlinks (default: a new temporary folder).
    """

    def __init__(self, instrument: Instrument, link_dir: str | None = None):
        self.instrument = instrument
        self._own_dir = link_dir is None        # a folder this server made goes away with it
        self.link_dir = link_dir or tempfile.mkdtemp(prefix="gonio-sim-")
        os.makedirs(self.link_dir, exist_ok=True)
        self._fds: dict[str, tuple[int, int]] = {}      # port -> (master, slave)
        self._pending: dict[str, bytes] = {}            # port -> bytes its client has not taken yet
        self.dropped: dict[str, int] = {}               # port -> bytes dropped for a client that does not read
        self._back_at: dict[str, float] = {}            # vanished port -> wall time it returns
        self._stop = threading.Event()
        self._threads: dict[str, threading.Thread] = {}     # port -> its serving thread
        try:
            for name, ep in instrument.ports.items():
                self._open(name)
                ep.on_vanish.append(self._vanished)
        except BaseException:               # (Ctrl-C, no free pty): leave no pty and no folder behind
            self.stop()
            raise

    # ------------------------------------------------------------------ ptys
    @property
    def paths(self) -> dict:
        """Stable paths (symlinks) of the ports, by port name."""
        return {name: os.path.join(self.link_dir, name) for name in self.instrument.ports}

    @property
    def devices(self) -> dict:
        """Current ``/dev/pts/N`` of the ports that exist now."""
        return {name: os.ttyname(fds[1]) for name, fds in self._fds.items()}

    def _open(self, name: str) -> None:
        master, slave = pty.openpty()
        tty.setraw(slave)               # no echo, no line editing, no CR/LF translation
        os.set_blocking(master, False)
        self._fds[name] = (master, slave)
        link = os.path.join(self.link_dir, name)
        tmp = link + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, link)

    def _close(self, name: str) -> None:
        self._pending.pop(name, None)
        fds = self._fds.pop(name, None)
        if fds:
            for fd in fds:
                try:
                    os.close(fd)
                except OSError:
                    pass
        link = os.path.join(self.link_dir, name)
        if os.path.lexists(link):
            os.unlink(link)

    def _vanished(self, endpoint, duration: float) -> None:
        clock = self.instrument.clock
        wall = duration if clock.instant else duration / clock.scale
        self._back_at[endpoint.name] = time.monotonic() + wall

    # ------------------------------------------------------------------ loop
    def _pump(self, name: str) -> None:
        master, _ = self._fds[name]
        try:
            data = os.read(master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        if not data:
            return
        ep = self.instrument.ports[name]
        ep.feed(data)
        if name in self._back_at:           # the port vanished while handling this line
            self._close(name)
            return
        self._flush(name)

    def _flush(self, name: str) -> None:
        """Write what the pty takes now of the endpoint's queued reply and alert bytes; keep the
        rest for the next pass (never wait on one client: a client that does not read must not
        stop the other ports). What waits is bounded: beyond :data:`MAX_PENDING` bytes the
        oldest whole lines are dropped (counted in ``dropped``), as a device's own output
        buffer overruns."""
        master, _ = self._fds[name]
        ep = self.instrument.ports[name]
        ep.poll()
        out = self._pending.pop(name, b"") + ep.take(len(ep.out))
        if len(out) > MAX_PENDING:
            cut = out.find(b"\n", len(out) - MAX_PENDING)
            kept = out[cut + 1:] if cut >= 0 else b""
            self.dropped[name] = self.dropped.get(name, 0) + len(out) - len(kept)
            out = kept
        while out:
            try:
                n = os.write(master, out)
                out = out[n:]
            except BlockingIOError:
                break
            except OSError:
                out = b""
        if out:
            self._pending[name] = out

    #: longest a port's loop sleeps between looks at its vanish schedule and its replies, s
    IDLE_S = 0.05

    def _serve_port(self, name: str) -> None:
        """One port's loop, in its own thread: reopen or close its pty as the ``vanish`` fault
        says, send what its device queued (alerts of motions that ended in real time), wait for
        bytes from its client (no longer than until its next alert is due) and feed them."""
        ep = self.instrument.ports[name]
        while not self._stop.is_set():
            back = self._back_at.get(name)
            if back is not None:
                now = time.monotonic()
                if now < back:
                    if name in self._fds:
                        self._close(name)
                    self._stop.wait(min(self.IDLE_S, back - now))
                    continue
                if name not in self._fds:
                    self._back_at.pop(name, None)
                    with self.instrument.lock:
                        ep.vanished_until = None
                    self._open(name)
            fds = self._fds.get(name)
            if fds is None:
                self._stop.wait(0.01)
                continue
            self._flush(name)
            due = ep.next_due()
            timeout = self.IDLE_S if due is None else min(self.IDLE_S, max(1e-3, due))
            try:
                ready, _, _ = select.select([fds[0]], [fds[0]] if name in self._pending else [], [], timeout)
            except (OSError, ValueError):
                self._stop.wait(0.01)
                continue
            if ready and name in self._fds:
                self._pump(name)

    def start(self) -> "PtyServer":
        """Serve every port in its own daemon thread; returns self."""
        for name in self.instrument.ports:
            if name not in self._threads:
                t = threading.Thread(target=self._serve_port, args=(name,), name=f"gonio-sim-pty-{name}",
                                     daemon=True)
                self._threads[name] = t
                t.start()
        return self

    def run(self) -> None:
        """Serve until ``stop()`` (blocking; the ports are served by their own threads)."""
        self.start()
        while not self._stop.wait(0.2):
            pass

    def stop(self) -> None:
        """Stop serving and close the ptys."""
        self._stop.set()
        for t in list(self._threads.values()):
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        for name in list(self._fds):
            self._close(name)
        for ep in self.instrument.ports.values():
            if self._vanished in ep.on_vanish:
                ep.on_vanish.remove(self._vanished)
        if self._own_dir:
            for name in self.instrument.ports:
                for link in (os.path.join(self.link_dir, name), os.path.join(self.link_dir, name) + ".new"):
                    if os.path.lexists(link):
                        os.unlink(link)
            try:
                os.rmdir(self.link_dir)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


def serve(settings: dict | None = None, sample: dict = DEFAULT_SAMPLE,
          reference: dict = DEFAULT_REFERENCE, seed: int = 0, clock=None, faults=None,
          link_dir: str | None = None, block: bool = True, echo="print", **kwargs):
    """Run a simulated instrument on pseudo-terminals.

    Parameters
    ----------
    settings, sample, reference, seed, faults, **kwargs
        As for ``Instrument``.
    clock : SimClock, str, float or None
        ``SimClock.coerce`` spec; default real time, as a lab rehearsal needs.
    link_dir : str or None
        Folder of the stable port symlinks (default: a new temporary folder).
    block : bool
        True: print the paths and serve until interrupted (Ctrl-C), for ``gonio sim serve``.
        False: serve in a background thread and return the ``PtyServer``.
    echo : callable, "print" or None
        Where the ``<port> <path> -> <device>`` lines go (default: stdout, flushed).

    Returns
    -------
    PtyServer
        With ``paths`` (stable symlinks) and ``devices`` (``/dev/pts/N``); ``stop()`` ends it.
    """
    clock = SimClock.coerce(clock, default="real")
    inst = Instrument(settings, sample=sample, reference=reference, seed=seed, clock=clock,
                      faults=faults, **kwargs)
    if echo == "print":
        def echo(line):
            print(line, flush=True)
    server = PtyServer(inst, link_dir)
    try:                                  # from here on, any exit closes the ptys and removes the folder
        if echo is not None:
            for name, path in server.paths.items():
                echo(f"{name} {path} -> {server.devices[name]}")
        if not block:
            return server.start()
        server.run()
    except KeyboardInterrupt:
        server.stop()
        if not block:
            raise
    except BaseException:
        server.stop()
        raise
    else:
        server.stop()
    return server
