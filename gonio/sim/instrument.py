"""The simulated gonioreflectometer: physics state plus one protocol port per declared port.

With a monochromator (settings' ``[monochromator]``) whose shutter is open, the light on the
sample is monochromatic at its wavelength (the simulator's convention: shutter closed, the
white LED lights the sample directly): the sample is rendered with its spectra at that
wavelength (`gonio.sim.physics.sample.at_wavelength`), the source's power is the lamp's times
its relative spectrum (`gonio.sim.physics.colour.source_spd`), the camera is a monochrome
sensor (`gonio.sim.physics.sensor.monochrome_qe`) and the power meter reads the beam at it.
"""

from __future__ import annotations

import copy
import math
import threading
import time
from collections import OrderedDict

import numpy as np
import serial

from gonio.core.channels import CHANNELS
from gonio.core.devices import PORTS
from gonio.core.errors import GonioError
from gonio.sim.devices.camera_port import CameraPort
from gonio.sim.devices.monochromator import CornerstoneTwin, MonochromatorEndpoint
from gonio.sim.physics.clock import SimClock
from gonio.sim.physics.colour import chart_radiance, source_spd
from gonio.sim.physics.errors import error_model, square_masks
from gonio.sim.physics.faults import FaultSchedule
from gonio.sim.physics.kinematics import forward
from gonio.sim.physics.lamp import Lamp
from gonio.sim.devices.port import PortEndpoint
from gonio.sim.physics.sample import SampleTruth, at_wavelength
from gonio.sim.physics.scene import HolderScene
from gonio.sim.devices.scpi_meter import PowerMeter, ScpiMeter
from gonio.sim.physics.sensor import SensorModel, encode_dng, monochrome_qe
from gonio.sim.physics.stages import RotaryAxis
from gonio.sim.devices.zaber_chain import ZaberChain

__all__ = ["Instrument", "DEFAULT_SETTINGS", "DEFAULT_SAMPLE", "DEFAULT_REFERENCE", "SIM_DEVICES", "lookup"]

#: docs/interfaces.md section 3.
DEFAULT_SETTINGS = {
    "axes": {
        "yaw": [1, 1, -95.0, 95.0],
        "tilt": [1, 2, -88.0, 88.0],
        "azimuth": [1, 3, -180.0, 180.0],
        "lamp": [1, 4, -175.0, 175.0],
        "cycle_dist": 720000,
        "lamp_block_deg": 6.0,
    },
    "camera": {"width": 64, "height": 48, "pixel_size": 0.01, "bits": 14},
    "holder": {"sample_half": 0.25, "offset": 0.3, "holder_reflectance": 0.05},
}
DEFAULT_SAMPLE = {"model": "diffuse", "params": {"reflectance": 0.5}}
DEFAULT_REFERENCE = {"model": "diffuse", "params": {"reflectance": 0.99}}
_AXIS_NAMES = ("yaw", "tilt", "azimuth", "lamp")

_REGISTRY: dict[str, "Instrument"] = {}

#: The simulated twin of each port :data:`gonio.core.devices.PORTS` declares: the attribute the
#: instrument keeps it under, its class, the line end of its replies, and whether a bare CR ends
#: a request line (the meter takes CR, LF or CRLF; the camera's protocol ends lines with LF only).
SIM_DEVICES = {
    "zaber": ("zaber", ZaberChain, b"\r\n", True),
    "meter": ("scpi", ScpiMeter, b"\n", True),
    "camera": ("camera", CameraPort, b"\n", False),
}
#: The twin of each optional port: attribute, class, endpoint class (its own line handling).
OPTIONAL_SIM_DEVICES = {"monochromator": ("monochromator", CornerstoneTwin, MonochromatorEndpoint)}


def lookup(name: str) -> "Instrument":
    """The instrument registered under ``name`` (KeyError if none)."""
    return _REGISTRY[name]


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


class Instrument:
    """A simulated gonioreflectometer.

    Parameters
    ----------
    settings : dict or None
        Instrument settings (docs/interfaces.md section 3); merged over ``DEFAULT_SETTINGS``.
    sample, reference : dict
        Sample specs (``{"model": ..., "options": ..., "params": ...}``,
        ``{"bsdf_file": PATH}`` or ``{"mitsuba": DICT}``) of the sample and reference squares.
    seed : int
        Seeds every random draw (lamp drift, fixed-pattern noise, frame noise, meter noise).
    clock : SimClock, str, float or None
        A clock or a spec for ``SimClock.coerce``: None or ``"instant"``, ``"real"``,
        ``"scaled:10"``, a scale factor.
    faults : FaultSchedule, list, dict, str or None
        Fault schedule (TOML path or text, or parsed tables); see ``_faults.py``.
    sensor, lamp, meter : dict or None
        Overrides of ``SensorModel``, ``Lamp``, ``PowerMeter`` parameters.
    spp : int
        Samples per pixel of the renders (edge anti-aliasing only).

    Notes
    -----
    ``settings["errors"]`` (a preset name or table, ``_errors.error_model``) switches on the
    systematic errors; their truth, drawn from ``seed``, is ``error_state``. Without it (or
    with ``ideal``) the instrument is the error-free one, bit for bit.
    """

    def __init__(self, settings: dict | None = None, sample: dict = DEFAULT_SAMPLE,
                 reference: dict = DEFAULT_REFERENCE, seed: int = 0, clock=None, faults=None,
                 sensor: dict | None = None, lamp: dict | None = None,
                 meter: dict | None = None, spp: int = 4):
        self.settings = _merge(DEFAULT_SETTINGS, settings or {})
        self.seed = int(seed)
        self.clock = SimClock.coerce(clock)
        self.lock = threading.RLock()
        self._waiting = threading.Condition(self.lock)
        self.clock.sleep = self.wait        # a device that waits lets the others go on
        self.name: str | None = None

        ax = self.settings["axes"]
        cd = int(ax["cycle_dist"])
        try:
            entries = sorted((int(ax[n][1]), n, ax[n]) for n in _AXIS_NAMES)
        except KeyError as e:
            raise ValueError(f"settings.axes lacks {e.args[0]!r}") from None
        if [e[0] for e in entries] != [1, 2, 3, 4] or any(int(e[2][0]) != 1 for e in entries):
            raise ValueError("the simulator puts the four stages on device 1, axes 1..4")
        self.axis_names = [e[1] for e in entries]
        self.axes = [RotaryAxis(limit_min=int(round(v[2] * cd / 360.0)),
                                limit_max=int(round(v[3] * cd / 360.0)), cycle_dist=cd)
                     for _, _, v in entries]
        # power-on: wherever the last session left them (seeded, within 20 deg of home)
        start = np.random.default_rng([self.seed & 0xFFFFFFFF, 0x57A6]).uniform(-20.0, 20.0, 4)
        for a, deg in zip(self.axes, start):
            a.physical = float(round(deg * cd / 360.0))
            a.offset = a.physical

        self.lamp = Lamp(self.seed, **(lamp or {}))
        self.meter = PowerMeter(self.seed, **(meter or {}))
        cam = self.settings["camera"]
        self.sensor = SensorModel(width=int(cam["width"]), height=int(cam["height"]),
                                  bits=int(cam["bits"]), seed=self.seed, p_ref=self.lamp.p0,
                                  **(sensor or {}))
        self.sample = SampleTruth(sample)
        self.reference = SampleTruth(reference)
        self.spp = int(spp)
        self.faults = FaultSchedule.coerce(faults)
        self.errors = error_model(self.settings.get("errors"))
        rel_std = np.asarray((self.settings.get("reference") or {}).get("rel_std", 0.0), dtype=np.float64)
        if rel_std.ndim and self.errors.reference.draw_certificate:
            raise GonioError("the simulator draws one reference certificate error: give [reference] rel_std as one "
                             "number, or an error preset that does not draw it (ideal)")
        self.error_state = self.errors.draw(self.seed, float(rel_std) if rel_std.ndim == 0 else 0.0)
        self._errors_on = self.errors.active

        self.ports = {}
        self.monochromator = None
        for spec in PORTS:                          # one simulated device per declared port
            if spec.optional:                       # served where the settings declare the device
                if self.settings.get(spec.table) is not None:
                    attr, cls, endpoint = OPTIONAL_SIM_DEVICES[spec.name]
                    setattr(self, attr, cls(self))
                    self.ports[spec.name] = endpoint(self, getattr(self, attr))
                continue
            attr, cls, eol, split_cr = SIM_DEVICES[spec.name]
            setattr(self, attr, cls(self))
            self.ports[spec.name] = PortEndpoint(self, spec.name, getattr(self, attr), eol, split_cr=split_cr)
        self._scene: HolderScene | None = None
        self._spectral: dict = {}          # per wavelength (nm): (the sample's truth there, its scene or None)
        self.detector = "front"           # the detector arm's stop: "front" (reflection) or "rear" (transmission)
        self.holder_open = False          # the sample taken out of the holder: the camera sees the open beam
        self._radiance = OrderedDict()
        self._frame_key = None
        self._frame_count = 0

    def wait(self, seconds: float) -> None:
        """Wait ``seconds`` of wall time (a scaled clock's ``advance``: a meter averaging, a camera
        exposing), letting go of the instrument's lock meanwhile when this thread holds it: the
        other devices answer while one waits (each port serialises its own lines; see
        :mod:`gonio.sim.devices.port`)."""
        end = time.monotonic() + float(seconds)
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return
            try:
                self._waiting.wait(left)        # releases the (re-entrant) lock, however deep
            except RuntimeError:                # this thread does not hold it
                time.sleep(left)
                return

    # ------------------------------------------------------------------ registry
    def register(self, name: str) -> "Instrument":
        """Make the ports reachable as ``sim://NAME/zaber|meter|camera``; returns self."""
        if "/" in name or not name:
            raise ValueError("an instrument name is non-empty and has no '/'")
        _REGISTRY[name] = self
        self.name = name
        return self

    def unregister(self) -> None:
        """Remove the instrument from the ``sim://`` registry, and release its Mitsuba scene
        (:meth:`release`)."""
        if self.name is not None and _REGISTRY.get(self.name) is self:
            del _REGISTRY[self.name]
        self.name = None
        self.release()

    def release(self) -> None:
        """Let go of the Mitsuba objects (the holder scene, a sample's or reference's loaded
        BSDF) and the radiance cache; they are made again if the instrument is used again.

        The instrument and its devices refer to one another (a reference cycle), so without
        this its scene lived until Python's cyclic collector ran, rarely in a long process (it
        is paused while frozen kernels record). Every Mitsuba object alive stays in Dr.Jit's
        registry, and each render's BSDF and shape calls are traced over all of them: a
        process that ran one calibrated capture after another rendered 5 ms a frame at its
        first session and 17 ms at its ninth (tests/fitting/budget_coverage.py, 2026-12-02)."""
        self._scene = None
        self._spectral.clear()
        self._radiance.clear()
        self._frame_key = None
        for truth in (self.sample, self.reference):
            if getattr(truth, "_bsdf", None) is not None:
                truth._bsdf = None

    def url(self, port: str) -> str:
        """``sim://NAME/PORT`` of a registered instrument."""
        if self.name is None:
            raise RuntimeError("register the instrument first")
        return f"sim://{self.name}/{port}"

    def open(self, port: str, **kwargs):
        """``serial.serial_for_url`` of one of this (registered) instrument's ports."""
        return serial.serial_for_url(self.url(port), **kwargs)

    # ------------------------------------------------------------------ truth
    @property
    def fault_seed(self) -> int:
        return self.seed if self.faults.seed is None else int(self.faults.seed)

    @property
    def sample_spec(self) -> dict:
        """The sample spec the instrument was built with (a copy)."""
        return copy.deepcopy(self.sample.spec)

    def true_brdf(self, wi, wo) -> np.ndarray:
        """True f_r of the sample (sr^-1), shape (N, 3), for (N, 3) directions (sample frame)."""
        return self.sample.eval(wi, wo)

    def pose_microsteps(self) -> tuple:
        """Physical stage positions now (yaw, tilt, azimuth, lamp), integer microsteps."""
        t = self.clock.now()
        return tuple(int(round(a.position_physical(t))) for a in self.axes)

    def angles(self) -> dict:
        """Physical stage angles now, radians, by axis name."""
        return {n: p * 2 * math.pi / a.cycle_dist
                for n, p, a in zip(self.axis_names, self.pose_microsteps(), self.axes)}

    def geometry(self, pose: tuple | None = None) -> dict:
        """``wi``, ``wo``, image ``right``/``up`` (sample frame) and ``R`` for a pose (default: now)."""
        pose = self.pose_microsteps() if pose is None else pose
        ang = {n: p * 2 * math.pi / a.cycle_dist for n, p, a in zip(self.axis_names, pose, self.axes)}
        if not self._errors_on:
            return forward(ang["yaw"], ang["tilt"], ang["azimuth"], ang["lamp"], self.detector)
        st = self.error_state
        for n, a in zip(self.axis_names, self.axes):      # true = commanded + the stage's errors
            ang[n] += math.radians(st.axis_error_deg(_AXIS_NAMES.index(n), a.moves, a.last_dir))
        g = forward(ang["yaw"], ang["tilt"], ang["azimuth"], ang["lamp"], self.detector)
        H = st.holder
        if H is not None:                                  # the holder's true frame
            g = {k: (v @ H if k == "R" else H.T @ v) for k, v in g.items()}
        return g

    def geometry_angle(self, pose: tuple, name: str) -> float:
        """Angle (radians) of axis ``name`` in a pose of physical microsteps."""
        i = self.axis_names.index(name)
        return pose[i] * 2 * math.pi / self.axes[i].cycle_dist

    # ------------------------------------------------------------------ test helpers
    def set_pose(self, **angles_deg) -> None:
        """Put stages at angles (deg) at once, homed, without the protocol (tests, demos)."""
        t = self.clock.now()
        for n, deg in angles_deg.items():
            a = self.axes[self.axis_names.index(n)]
            a.power_cycle(t)
            a.physical = float(round(deg * a.cycle_dist / 360.0))
            a.offset, a.homed = 0.0, True

    def home_all(self) -> None:
        """All stages homed at their reference, at once (tests, demos)."""
        self.set_pose(**{n: 0.0 for n in self.axis_names})

    def power_cycle(self, device: int = 1) -> None:
        """Power-cycle device 1 (stages lose their reference) or device 2 (lamp off)."""
        t = self.clock.now()
        if device == 1:
            for a in self.axes:
                a.power_cycle(t)
        else:
            self.lamp.switch(t, False)
            self.lamp.set_flux(t, 1.0)

    # ------------------------------------------------------------------ camera physics
    @property
    def scene(self) -> HolderScene:
        if self._scene is None:
            self._scene = self._make_scene(self.sample)
        return self._scene

    def _make_scene(self, truth: SampleTruth) -> HolderScene:
        cam, hold = self.settings["camera"], self.settings["holder"]
        return HolderScene(
            truth.mitsuba, self.reference.mitsuba, width=int(cam["width"]),
            height=int(cam["height"]), pixel_size=float(cam["pixel_size"]),
            sample_half=float(hold["sample_half"]), offset=float(hold["offset"]),
            holder_reflectance=float(hold["holder_reflectance"]), spp=self.spp,
            markers=hold.get("markers"), holder_pose=hold.get("sim_pose"),   # sim_pose: the truth
            sample_truth=truth)

    # ------------------------------------------------------------------ monochromatic light
    @property
    def wavelength_nm(self) -> float | None:
        """The wavelength of the light on the sample, nm: the monochromator's where it has one
        with its shutter open (module notes), else None (the white LED)."""
        m = self.monochromator
        if m is None or not m.drive.shutter_open or not m.drive.nm > 0:
            return None
        return float(m.drive.nm)

    def light(self, t: float) -> tuple[float, float | None]:
        """(the power of the light on the sample at time ``t``, W; its wavelength, nm or None):
        the lamp's, times the source's relative spectrum there for monochromatic light."""
        nm, p = self.wavelength_nm, self.lamp.power(t)
        return (p if nm is None else p * source_spd(nm)), nm

    def truth_at(self, nm: float | None) -> SampleTruth:
        """The sample's truth at ``nm`` (its spectra there, `at_wavelength`); the RGB one for None."""
        if nm is None:
            return self.sample
        if nm not in self._spectral:
            self._spectral[nm] = [SampleTruth(at_wavelength(self.sample.spec, nm)), None]
        return self._spectral[nm][0]

    def _scene_at(self, nm: float | None) -> HolderScene:
        if nm is None:
            return self.scene
        self.truth_at(nm)
        if self._spectral[nm][1] is None:
            self._spectral[nm][1] = self._make_scene(self._spectral[nm][0])
        return self._spectral[nm][1]

    def radiance(self, pose: tuple | None = None, nm: float | None = None) -> np.ndarray:
        """Radiance image for unit irradiance at a pose (default: now), (H, W, 3), sr^-1; cached.
        ``nm``: of the sample at that wavelength (equal channels for a spectral sample).

        With the lamp arm within ``lamp_block_deg`` of the camera the lamp head hides the
        sample: the image is black (the controller should never go there).
        """
        pose = self.pose_microsteps() if pose is None else tuple(pose)
        key = pose if not self._errors_on else (pose, *((a.moves, a.last_dir) for a in self.axes))
        key = key if self.detector == "front" else (key, self.detector)
        key = key if nm is None else (key, "nm", float(nm))
        img = self._radiance.get(key)
        if img is None:
            g = self.geometry(pose)
            lamp_deg = abs((math.degrees(self.geometry_angle(pose, "lamp")) + 180.0) % 360.0 - 180.0)
            lamp_deg = lamp_deg if self.detector == "front" else 180.0 - lamp_deg
            if lamp_deg < float(self.settings["axes"].get("lamp_block_deg", 0.0)):
                # the lamp head stands between the sample and the camera: nothing to see
                img = np.zeros((self.sensor.height, self.sensor.width, CHANNELS))
            else:
                img = self._scene_at(nm).render(g["wi"], g["wo"], g["right"], g["up"])
                if self._errors_on:
                    img = self._with_errors(img, g, self.truth_at(nm))
            self._radiance[key] = img
            if len(self._radiance) > 16:
                self._radiance.popitem(last=False)
        else:
            self._radiance.move_to_end(key)
        return img

    def _with_errors(self, img: np.ndarray, g: dict, sample: SampleTruth | None = None) -> np.ndarray:
        """The render plus what it cannot show: each square's interior set to its true radiance
        (wedge, apertures, true reference), then the stray-light floor (``_errors.py``)."""
        st = self.error_state
        img = np.array(img, dtype=np.float64)
        if st.squares_altered:
            wi, wo = np.asarray(g["wi"], float), np.asarray(g["wo"], float)
            ms, mr = square_masks(g, self.settings)
            true, shown = st.sample_radiance(sample or self.sample, wi, wo)
            img[ms] += true - shown
            true, shown = st.reference_radiance(self.reference, wi, wo)
            img[mr] += true - shown
        if self.errors.stray.floor:
            img += self.errors.stray.floor / math.pi
        return img

    #: Radiance (per unit power, sr^-1) and power (W) of the flat-field source: an integrating
    #: sphere as bright as a white Lambertian at normal incidence under the full lamp, on its
    #: own stabilised supply (no warm-up, no drift).
    FLAT_RADIANCE = 1.0 / math.pi
    FLAT_POWER = 0.01

    def capture(self, seconds: float, source: str = "scene") -> bytes:
        """Expose one frame of ``seconds`` now; advance the clock; return the DNG bytes.

        ``source="flat"`` images the flat-field source (the lab puts an integrating sphere
        in front of the lens; it fills the frame with uniform radiance), for the
        photo-response non-uniformity calibration. ``source="chart"`` images the ColorChecker
        in the holder's chart slot under the lamp at normal incidence (gonio/sim/physics/colour.chart_radiance:
        spectral, the camera's own response to the chart), for the colour calibration.
        ``source="open_beam"`` images the lamp through the empty aperture from the rear stop
        (``[transmission]`` open_beam_attenuation / beam_solid_angle_sr), ASTM E2387; a plain
        exposure (``"scene"``) does too while ``holder_open`` (the operator took the sample out:
        the session's twin does, gonio/bench/session/stops.py).

        The noise comes from ``default_rng([seed, 0xCA3E, *pose + 2**31, exposure ns, lamp on,
        flux ppm, lamp dead, flat, frame count at this pose])``: the same pose, exposure, lamp
        state and frame order give the same noise in a new process.
        """
        if source not in ("scene", "flat", "chart", "open_beam"):
            raise ValueError(f"unknown camera source {source!r}")
        if source == "scene" and self.holder_open:
            source = "open_beam"               # nothing in the holder: the lamp through its aperture
        flat = source == "flat"
        with self.lock:
            t0 = self.clock.now()
            pose = self.pose_microsteps()
            lamp = self.lamp
            state = (int(lamp.on), int(round(lamp.flux * 1e6)), int(lamp.dead), int(flat))
            if pose != self._frame_key:
                self._frame_key, self._frame_count = pose, 0
            frame = self._frame_count
            self._frame_count += 1
            exposure_ns = int(round(seconds * 1e9))
            key = [self.seed & 0xFFFFFFFF, 0xCA3E, *[(p + 2**31) & 0xFFFFFFFF for p in pose],
                   exposure_ns, *state, frame] + ([0xC4A7] if source == "chart" else []) + ([0x0BE7] if source == "open_beam" else [])
            nm = self.wavelength_nm if source == "scene" else None     # monochromatic light on the sample
            if nm is not None:
                key += [0x5EC7, int(round(nm * 1000))]
            rng = np.random.default_rng(key)
            power = self.FLAT_POWER if flat else self.light(t0 + 0.5 * seconds)[0] if nm is not None \
                else lamp.power(t0 + 0.5 * seconds)
            if flat:
                rad = np.full((self.sensor.height, self.sensor.width, CHANNELS), self.FLAT_RADIANCE)
            elif source == "chart":
                rad = chart_radiance(self.sensor.colour, self.sensor.height, self.sensor.width)
            elif source == "open_beam":       # the sample out, the lamp behind the aperture (ASTM E2387)
                tr, g = self.settings.get("transmission") or {}, self.geometry(pose)
                L = float(tr.get("open_beam_attenuation", 1e-3)) / float(tr.get("beam_solid_angle_sr", 1e-3))
                rad = self.scene.open_beam(L, g["wo"], g["up"]) if power > 0.0 else 0.0 * self.scene.aperture(g["wo"], g["up"])
            elif power > 0.0:
                rad = self.radiance(pose, nm)
                if nm is not None:           # a monochrome sensor: every site sees the light's radiance x QE
                    rad = rad * monochrome_qe(nm)
            else:
                rad = np.zeros((self.sensor.height, self.sensor.width, CHANNELS))
            raw = self.sensor.expose(rad, power, seconds, rng, camera_rgb=source == "chart" or nm is not None)
            if self._errors_on:
                raw = self.error_state.nonlinear(raw, self.sensor.black, self.sensor.white)
            self.clock.advance(seconds)
            desc = {"gonio_sim": 1, "pose_microsteps": list(pose), "exposure_ns": exposure_ns,
                    "frame_at_pose": frame, "seed": self.seed, "source": source}
            return encode_dng(raw, black=self.sensor.black, white=self.sensor.white,
                              exposure=seconds, description=desc, colour=self.sensor.colour)
