"""Cameras behind one interface, and RAW decoding to linear values.

A camera has ``expose(seconds, path) -> sha256`` (writes one RAW file at ``path``, returns the
SHA-256 of the bytes it wrote, verified against the file) and ``close()``. Three of them:
`SimCamera` (the tethered-camera protocol of docs/interfaces.md section 4 over a serial URL;
``flat`` is its flat-field source), `WatchedFolderCamera` (RAW files the vendor's tethering
software drops in a folder) and `Gphoto2Camera` (the ``gphoto2`` command-line tool).

Every camera first writes to a temporary name beside ``path``, checks the checksum, then
fsyncs and renames: a file with the final name is always complete and verified. `deliver`
(and `SimCamera.expose_deferred`) returns a `Delivery` whose ``finish()`` does the check,
fsync and rename later (a capture's worker thread, while the stages move on). RAW decoding
(`decode_raw`, `RawFrame`, `read_verified`) lives in `gonio.bench.drivers.raw`; re-exported here.
"""

# SimCamera speaks over sim://NAME/camera or a pty: *IDN?, SENSOR?, EXPOSE <s> <path> ->
# OK <sha256>, and FLAT <s> <path> (the flat-field source) behind flat. A camera without flat
# gets no flat-field (PRNU) correction.
# WatchedFolderCamera waits for a new file whose size has settled and copies it to path.
# Gphoto2Camera runs gphoto2 --set-config shutterspeed=... and
# --capture-image-and-download --filename ....
# SimCamera.expose_deferred returns as soon as the camera has written the file; deliver gives
# the same object for any camera (one that cannot defer has committed the file already).

from __future__ import annotations

import errno
import hashlib
import math
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import serial

from gonio.core.files import commit_file, sha256_file, tmp_name
from gonio.core.errors import CommunicationError, DeviceError, GonioError
from gonio.core.preflight import control_character
from gonio.bench.drivers.raw import RawFrame, _dng_direct, decode_raw, read_verified  # noqa: F401  (re-exported)

__all__ = ["camera_from_spec", "open_camera", "SensorInfo", "RawFrame", "decode_raw", "read_verified", "SimCamera", "WatchedFolderCamera", "Gphoto2Camera",
           "RAW_SUFFIXES", "BadDelivery", "Delivery", "deliver"]

RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw")


@dataclass(frozen=True)
class SensorInfo:
    """Sensor geometry and levels: pixels, ADC bits, black and white levels (DN), CFA pattern."""

    width: int
    height: int
    bits: int
    black: int
    white: int
    cfa: str = "RGGB"


def _commit(tmp: Path, path: Path, durable: bool = True) -> None:
    """`commit_file`, with a failed fsync or rename (a full disk) named after ``path``; the
    temporary file is removed."""
    try:
        commit_file(tmp, path, durable=durable)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror, str(path)) from None
        raise


class BadDelivery(DeviceError):
    """A deferred RAW file is missing or does not match the camera's checksum (removed)."""


@dataclass
class Delivery:
    """A RAW file at ``path``: written by the camera under ``tmp`` and not yet checked (``tmp`` None:
    already checked and committed). ``digest`` is the camera's SHA-256 of it."""

    path: Path
    digest: str
    tmp: Path | None = None
    data: bytes | None = None        # the file's bytes, once `read`

    def read(self) -> bytes | None:
        """The unchecked file's bytes (kept for `finish`: the file is read once); None where the
        file is committed already (read it at ``path``)."""
        if self.tmp is not None and self.data is None:
            try:
                self.data = self.tmp.read_bytes()
            except FileNotFoundError:
                raise BadDelivery(f"{self.path.name} vanished before its check") from None
        return self.data

    def finish(self, durable: bool = True) -> bytes | None:
        """Check the file against ``digest``, then commit it (fsync, rename, fsync the folder);
        return its bytes, read once for the check and a decode (None: committed before).
        ``durable=False``: the rename alone, for a batch of files that the caller makes durable
        at once (`gonio.core.files.make_durable`) before it records them.

        Raises
        ------
        BadDelivery
            The file is missing or its bytes do not match (the temporary file is removed).
        """
        if self.tmp is None:
            return None
        data = self.read()
        if hashlib.sha256(data).hexdigest() != self.digest:
            self.discard()
            raise BadDelivery(f"{self.path.name} does not match the camera's checksum")
        _commit(self.tmp, self.path, durable)
        self.tmp, self.data = None, None
        return data

    def discard(self) -> None:
        """Remove the unchecked file (a point given up)."""
        if self.tmp is not None:
            self.tmp.unlink(missing_ok=True)
            self.tmp, self.data = None, None


def deliver(camera, seconds: float, path: str | os.PathLike) -> Delivery:
    """``camera.expose_deferred`` where the camera has it, else ``expose`` (checked and committed)."""
    deferred = getattr(camera, "expose_deferred", None)
    if deferred is not None:
        return deferred(seconds, path)
    return Delivery(Path(path), camera.expose(seconds, path))


class SimCamera:
    """The tethered camera protocol (interfaces.md section 4) over a serial URL.

    Parameters
    ----------
    port_url : str
        ``sim://NAME/camera`` or a pty path.
    timeout : float
        Seconds to wait for a reply, on top of the exposure time.
    retries : int
        Exposures retried after a missing, truncated or mismatching file.
    """

    #: Longest command line (UTF-8 bytes, without the newline): ``EXPOSE``, the exposure and a
    #: path of up to 4096 bytes (PATH_MAX). The simulated camera refuses longer lines
    #: (``gonio.sim.devices.camera_port.CameraPort.MAX_LINE``, the same figure).
    MAX_LINE = 4200

    def __init__(self, port_url: str, baudrate: int = 115200, timeout: float = 30.0, *, retries: int = 2):
        self.port_url = port_url
        self.baudrate = baudrate
        self.timeout = timeout
        self.retries = retries
        self.retries_used = 0                 # exposures taken again after a bad file
        try:
            self._port = serial.serial_for_url(port_url, baudrate=baudrate, timeout=timeout)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CommunicationError(f"cannot open the camera port {port_url!r} ({exc}); "
                                     "check the connection and the camera URL") from None
        for _ in range(3):                       # resync: the first reply may be stale
            self.idn = self._query("*IDN?")
            if self.idn.count(",") >= 3:
                break
        tok = self._query("SENSOR?").split()
        try:
            self.sensor = SensorInfo(int(tok[0]), int(tok[1]), int(tok[2]), int(tok[3]), int(tok[4]),
                                     tok[5] if len(tok) > 5 else "RGGB")
        except (IndexError, ValueError):
            raise CommunicationError(f"camera on {port_url} answered SENSOR? with {' '.join(tok)!r}; "
                                     "check that the URL names a camera port") from None

    def _once(self, text: str, timeout: float | None) -> bytes | None:
        """One exchange; None if the port failed or stayed silent."""
        try:
            if timeout is not None:
                self._port.timeout = timeout
            if self._port.in_waiting:            # a late reply, or one a killed process left
                self._port.reset_input_buffer()
            self._port.write((text + "\n").encode("utf-8"))
            line = self._port.readline()
        except (serial.SerialException, OSError, AttributeError):
            return None
        finally:
            if timeout is not None and self._port is not None:
                self._port.timeout = self.timeout
        return line if line.endswith(b"\n") else None

    @classmethod
    def _check_line(cls, text: str) -> str:
        """``text`` as one command line of the camera protocol, else `GonioError`: no control
        character (a newline in a path would end the line and start a second command: issue
        36), UTF-8 encodable, at most `MAX_LINE` bytes."""
        bad = control_character(text)
        if bad is not None:
            raise GonioError(f"camera command {text[:60]!r} holds the control character {bad!r}; "
                             "give file paths without control characters (newline, CR, ESC, ...)")
        try:
            n = len(text.encode("utf-8"))
        except UnicodeEncodeError:
            raise GonioError(f"camera command {text[:60]!r} cannot be sent as UTF-8 (a file name in another "
                             "encoding); give a path of UTF-8 characters") from None
        if n > cls.MAX_LINE:
            raise GonioError(f"camera command {text[:60]!r}... is {n} bytes long, more than the camera "
                             f"protocol's {cls.MAX_LINE}; give a shorter path")
        return text

    def _query(self, text: str, timeout: float | None = None) -> str:
        """Send a line, return the reply; after a silent or failed port, reconnect once and resend."""
        text = self._check_line(text)
        line = self._once(text, timeout)
        if line is None:
            self.retries_used += 1
            try:
                self._port.close()
            except (serial.SerialException, OSError):
                pass
            try:
                self._port = serial.serial_for_url(self.port_url, baudrate=self.baudrate, timeout=self.timeout)
            except (serial.SerialException, OSError, ValueError) as exc:
                raise CommunicationError(f"camera on {self.port_url} failed and cannot be reopened ({exc}); "
                                         "check the connection, then resume the session") from None
            line = self._once(text, timeout)
        if line is None:
            raise CommunicationError(f"camera on {self.port_url} did not answer {text.split()[0]!r}, "
                                     "even after a reconnect; check it is on, then resume the session")
        return line.decode("utf-8", "replace").strip()

    def expose(self, seconds: float, path: str | os.PathLike) -> str:
        """Expose for ``seconds`` and store the RAW file at ``path``; return its SHA-256.

        Raises
        ------
        DeviceError
            ``ERR`` from the camera, or a bad file after every retry.
        """
        return self._shoot("EXPOSE", seconds, path)

    def flat(self, seconds: float, path: str | os.PathLike) -> str:
        """Expose the flat-field source (uniform radiance over the frame) for ``seconds``: as `expose`."""
        return self._shoot("FLAT", seconds, path)

    def flat_deferred(self, seconds: float, path: str | os.PathLike) -> Delivery:
        """As `flat`, returning once the camera has written the file (see `expose_deferred`)."""
        return self._shoot("FLAT", seconds, path, check=False)

    def chart(self, seconds: float, path: str | os.PathLike) -> str:
        """Expose the ColorChecker in the holder's chart slot (the colour calibration): as `expose`."""
        return self._shoot("CHART", seconds, path)

    def expose_deferred(self, seconds: float, path: str | os.PathLike) -> Delivery:
        """As `expose`, returning once the camera has written the file: its checksum check, fsync
        and rename are the returned `Delivery`'s ``finish()`` (a missing file is retried here)."""
        return self._shoot("EXPOSE", seconds, path, check=False)

    def _shoot(self, command: str, seconds: float, path: str | os.PathLike, check: bool = True):
        self._check_line(f"{command} {seconds:.9g} {os.fspath(path)}")   # before resolve() meets a NUL
        path = Path(path).resolve()
        tmp = tmp_name(path)
        why = ""
        for _ in range(self.retries + 1):
            reply = self._query(f"{command} {seconds:.9g} {tmp}", timeout=self.timeout + seconds)
            if reply.startswith("ERR disk full"):        # the capture stops resumably, naming the disk
                tmp.unlink(missing_ok=True)
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            if reply.startswith("ERR"):
                raise DeviceError(f"camera refused a {seconds:g} s exposure to {path.name}: {reply[4:]}; "
                                  "check the exposure range and the session folder")
            if not reply.startswith("OK "):
                why = f"unexpected reply {reply!r}"
                continue
            digest = reply.split()[1].lower()
            if not tmp.exists():
                why = "the camera reported a file it did not write"
                self.retries_used += 1
                continue
            if not check:
                return Delivery(path, digest, tmp)
            if sha256_file(tmp) != digest:
                why = "checksum mismatch"
                tmp.unlink()
                self.retries_used += 1
                continue
            _commit(tmp, path)
            return digest
        if tmp.exists():
            tmp.unlink()
        raise DeviceError(f"camera could not deliver {path.name} after {self.retries + 1} tries ({why}); "
                          "check the camera and disk, then resume the session")

    def identify(self) -> str:
        """The camera's ``*IDN?`` answer (read when the port opened)."""
        return self.idn

    def close(self) -> None:
        """Close the port."""
        self._port.close()


class WatchedFolderCamera:
    """A camera whose vendor software drops RAW files into a folder.

    Parameters
    ----------
    folder : path
        The folder the tethering software writes to.
    trigger : callable, optional
        ``trigger(seconds)`` asks for an exposure (sets the shutter and fires); None when an
        operator or the vendor software fires by itself.
    timeout_s : float
        How long to wait for the new file.
    poll_s : float
        Seconds between looks at the folder; ``sleep`` is called with it.
    """

    def __init__(self, folder: str | os.PathLike, trigger: Callable[[float], None] | None = None, *,
                 timeout_s: float = 60.0, poll_s: float = 0.2, sleep: Callable[[float], None] = time.sleep):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise GonioError(f"watched folder {self.folder} does not exist; create it or fix the path")
        self.trigger = trigger
        self.timeout_s = timeout_s
        self.poll_s = poll_s
        self.sleep = sleep
        self.sensor = None
        self._seen = self._raw_files()

    def _raw_files(self) -> dict[str, int]:
        return {p.name: p.stat().st_size for p in self.folder.iterdir()
                if p.is_file() and p.suffix.lower() in RAW_SUFFIXES}

    def expose(self, seconds: float, path: str | os.PathLike) -> str:
        """Fire (if a trigger is given), wait for the new RAW file, copy it to ``path``."""
        if self.trigger is not None:
            self.trigger(seconds)
        n = max(1, math.ceil(self.timeout_s / self.poll_s))
        sizes: dict[str, int] = {}
        for _ in range(n):
            now = self._raw_files()
            new = {k: v for k, v in now.items() if k not in self._seen}
            settled = [k for k, v in new.items() if v > 0 and sizes.get(k) == v]
            if settled:
                name = sorted(settled)[0]
                self._seen[name] = new[name]
                src = self.folder / name
                path = Path(path)
                tmp = tmp_name(path)
                try:
                    shutil.copyfile(src, tmp)
                except OSError:                  # e.g. the disk is full: no half-copied file stays
                    tmp.unlink(missing_ok=True)
                    raise
                digest = sha256_file(tmp)
                if digest != sha256_file(src):
                    tmp.unlink()
                    raise DeviceError(f"{src} changed while it was copied; check the tethering software")
                _commit(tmp, path)
                return digest
            sizes = new
            self.sleep(self.poll_s)
        raise DeviceError(f"no new RAW file appeared in {self.folder} within {self.timeout_s:g} s; "
                          "check the tethering software, then resume the session")

    def identify(self) -> str:
        """What this camera is: the folder it watches (the vendor's software says no more)."""
        return f"{type(self).__name__} {self.folder}"

    def close(self) -> None:
        pass


def shutter_value(seconds: float) -> str:
    """gphoto2's shutterspeed notation: ``1/250`` below 1 s (the nearest 1/n), ``2.5`` above."""
    if not (math.isfinite(seconds) and seconds > 0):
        raise GonioError(f"exposure {seconds!r} s is invalid; use a positive time")
    if seconds >= 1.0:
        return f"{seconds:g}"
    return f"1/{max(1, round(1.0 / seconds))}"


class Gphoto2Camera:
    """A tethered camera driven through the ``gphoto2`` command-line tool.

    Parameters
    ----------
    gphoto2 : str
        The executable.
    port : str, optional
        gphoto2's ``--port`` (e.g. ``usb:001,004``), when more than one camera is attached.
    run : callable
        ``subprocess.run``-like; replaced in tests.
    timeout_s : float
        Per gphoto2 call, on top of the exposure time.
    """

    def __init__(self, gphoto2: str = "gphoto2", port: str | None = None, *,
                 run: Callable = subprocess.run, timeout_s: float = 60.0):
        self.gphoto2 = gphoto2
        self.port = port
        self.run = run
        self.timeout_s = timeout_s
        self.sensor = None
        if run is subprocess.run and shutil.which(gphoto2) is None:
            raise GonioError(f"{gphoto2!r} is not installed; install gphoto2 (apt-get install gphoto2) "
                             "or use another camera")

    def _call(self, args: list[str], timeout: float, path: Path | None = None) -> None:
        cmd = [self.gphoto2] + (["--port", self.port] if self.port else []) + args
        try:
            res = self.run(cmd, capture_output=True, text=True, timeout=timeout)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise DeviceError(f"gphoto2 failed ({type(exc).__name__}); check the camera's USB link") from None
        if res.returncode != 0:
            text = f"{res.stderr or ''}\n{res.stdout or ''}"
            if path is not None and ("No space left on device" in text or "Disk quota exceeded" in text):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))   # stops resumably
            msg = (res.stderr or res.stdout or "").strip().splitlines()
            raise DeviceError(f"gphoto2 {' '.join(args[:2])} failed: {msg[-1] if msg else res.returncode}; "
                              "check the camera's USB link and mode")

    def expose(self, seconds: float, path: str | os.PathLike) -> str:
        """Set the shutter, capture, download to a temporary name, rename; return the SHA-256."""
        path = Path(path)
        tmp = tmp_name(path)
        self._call(["--set-config", f"shutterspeed={shutter_value(seconds)}"], self.timeout_s)
        try:
            self._call(["--capture-image-and-download", "--filename", str(tmp), "--force-overwrite"],
                       self.timeout_s + seconds, path)
        except OSError:
            tmp.unlink(missing_ok=True)
            raise
        if not tmp.exists():
            raise DeviceError(f"gphoto2 reported success but wrote no file for {path.name}; "
                              "check the camera's capture target setting")
        digest = sha256_file(tmp)
        _commit(tmp, path)
        return digest

    def identify(self) -> str:
        """What this camera is: gphoto2 and its port (``gphoto2 --summary`` is not asked)."""
        return f"{type(self).__name__} {self.port or 'auto'}"

    def close(self) -> None:
        pass


def camera_from_spec(spec: str):
    """``--camera``'s value, read here and nowhere else: a :class:`Gphoto2Camera` for
    ``gphoto2``, a :class:`WatchedFolderCamera` for ``folder:PATH``, else the serial port or
    URL of a camera port itself (a capture's rig opens it as a :class:`SimCamera`)."""
    if spec == "gphoto2":
        return Gphoto2Camera()
    if spec.startswith("folder:"):
        return WatchedFolderCamera(spec[len("folder:"):])
    return spec


def open_camera(spec: str, *, timeout: float = 30.0):
    """The camera ``--camera`` names, opened (:func:`camera_from_spec`; a port as a
    :class:`SimCamera` with ``timeout``)."""
    camera = camera_from_spec(spec)
    return SimCamera(camera, timeout=timeout) if isinstance(camera, str) else camera
