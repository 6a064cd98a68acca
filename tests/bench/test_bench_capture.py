"""Capture, resume and export against the simulated instrument (sim://), the production code path."""

import json
import os

import numpy as np
import pytest
import xarray as xr

sim = pytest.importorskip("gonio.sim")

from gonio.bench.plan import kinematics
from gonio.bench.plan import plans
from gonio.bench.drivers.camera import SimCamera
from gonio.core.files import sha256_file
from gonio.bench.session.journal import Journal, read_session
from gonio.bench.settings import default_settings
from gonio.bench.session.capture import capture, resume
from benchfakes.cameras import InterruptingCamera
from gonio.core.errors import CommunicationError, DeviceError, GonioError, SessionError, UnreachableError
from gonio.bench.dataset.export import export

S = default_settings()
GLOSSY = {"model": "roughplastic", "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.15}}
SMALL = plans.Plan("small", plans.with_reciprocal(
    [[30, 0, 40, 180], [30, 0, 30, 180], [45, 0, 20, 0], [20, 0, 50, 90], [60, 0, 60, 180], [10, 0, 70, 135]]))


@pytest.fixture
def instrument(request):
    made = []

    def make(name, seed=1, sample=GLOSSY, faults=None):
        inst = sim.Instrument(S, sample=sample, seed=seed, faults=faults).register(name)
        made.append(inst)
        return inst
    yield make
    for inst in made:
        inst.unregister()


def run(inst, folder, plan=SMALL, **kw):
    return capture(folder, plan, S, inst.url("zaber"), inst.url("meter"), kw.pop("camera", inst.url("camera")),
                   seed=inst.seed, progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec, **kw)


def chi2(folder, inst):
    rows = Journal(folder / "journal.sqlite").points()
    wi = np.array([kinematics.directions(r["theta_i"], r["phi_i"]) for r in rows])
    wo = np.array([kinematics.directions(r["theta_o"], r["phi_o"]) for r in rows])
    # the journal holds white-balanced camera RGB: the sRGB truth seen through the camera (gonio/sim/physics/colour.py)
    truth = inst.true_brdf(wi, wo) @ inst.sensor.colour.balanced.T
    f, s = np.array([r["brdf"] for r in rows]), np.array([r["brdf_std"] for r in rows])
    return np.mean(((f - truth) / s) ** 2), rows


def assert_clean(folder):
    """No orphan temporary file; every journalled RAW file matches its checksum."""
    leftovers = [p.name for p in (folder / "raw").iterdir() if p.name.startswith(".tmp-") or p.name.endswith(".part")]
    assert leftovers == []
    with Journal(folder / "journal.sqlite") as j:
        for r in j.points():
            for e in r["detail"]["exposures"]:
                assert sha256_file(folder / e["file"]) == e["sha256"]


def test_capture_recovers_known_brdf_and_exports(instrument, tmp_path):
    inst = instrument("cap1")
    folder = tmp_path / "s"
    res = run(inst, folder, plans.load_plan("quick"))
    assert res.complete and res.n_new == res.n_done == 30 and res.stopped == ""
    c2, rows = chi2(folder, inst)
    assert 0.3 < c2 < 2.5, c2                              # f_r within its stated uncertainty of the truth
    assert len(res.reciprocity) == 4 and res.reciprocity_error < 0.02
    assert res.move_ordered_s < 0.7 * res.move_naive_s
    assert_clean(folder)
    doc = read_session(folder)
    assert doc["session"]["seed"] == 1 and doc["plan"]["name"] == "quick" and "axes" in doc["settings"]
    assert json.loads(doc["sample_truth"]["json"]) == GLOSSY
    ds = xr.open_dataset(export(folder), engine="h5netcdf")
    # the budget's inputs (interfaces.md 5.1): dark_input, a correlated mode of the dark frames' noise;
    # an uncalibrated session's uncorrected stage systematics (instrument.toml [systematics]): angle_input,
    # the shared signed modes, and axis_input, each axis's per-move error, over the four angles
    budget_dims = {"dark_input", "angle_input", "axis_input", "angle"}
    assert {k: v for k, v in ds.sizes.items() if k not in budget_dims} == {"point": 30, "channel": 3, "xyz": 3}
    assert 1 <= ds.sizes.get("dark_input", 0) <= 30 and list(ds.channel_label.values) == ["R", "G", "B"]
    assert ds.sizes["angle"] == 4 and ds.sizes["axis_input"] == 4 and ds.sizes["angle_input"] >= 1
    assert ds.angle_shift_independent.dims == ("axis_input", "point", "angle")
    for c in ("theta_i", "phi_i", "theta_o", "phi_o"):
        assert ds[c].attrs["units"] == "degree"
    assert ds.brdf.attrs["units"] == "sr^-1" and ds.brdf_std.dims == ("point", "channel")
    assert ds.saturated.dtype == np.int8 and ds.saturated.attrs["flag_meanings"] == "not_saturated saturated"
    assert ds.attrs["scale_rel_std"] == 0.005 and ds.attrs["seed"] == 1
    p = ds.reciprocal_partner.values
    assert (p >= 0).sum() == 8 and all(p[p[i]] == i for i in np.flatnonzero(p >= 0))
    assert json.loads(ds.attrs["sample_truth"]) == GLOSSY and ds.attrs["complete"] == 1
    # colour: a neutral stays neutral, and Y of a grey is its sRGB value (rows of the matrices)
    assert ds.brdf_xyz.dims == ("point", "xyz") and list(ds.xyz_label.values) == ["X", "Y", "Z"]
    Y = ds.brdf_xyz.set_xindex("xyz_label").sel(xyz_label="Y")          # the labels: CF-1.8 label variables
    np.testing.assert_allclose(Y, ds.brdf_srgb.values @ [0.2126, 0.7152, 0.0722], rtol=1e-12)
    assert np.all(ds.brdf_srgb_std > 0)
    ds.close()
    assert not any(n.startswith(".tmp-") for n in os.listdir(folder))


def test_hdr_bracketing_on_a_shiny_sample(instrument, tmp_path):
    """A specular peak about 200 times brighter than the reference: bracketed, merged, unsaturated."""
    inst = instrument("shiny", sample={"model": "roughplastic",
                                       "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.03}})
    folder = tmp_path / "s"
    assert run(inst, folder).complete
    c2, rows = chi2(folder, inst)
    assert c2 < 2.5
    assert not any(r["saturated"] for r in rows)
    peak = max(rows, key=lambda r: r["brdf"][1])
    assert peak["brdf"][1] > 30 and len(peak["detail"]["bracket"]) >= 3      # sr^-1: the specular point
    assert min(len(r["detail"]["bracket"]) for r in rows) == 1


def test_ctrl_c_once_stops_resumably_and_resume_finishes(instrument, tmp_path):
    ref = instrument("ref2")
    run(ref, tmp_path / "ref")
    inst = instrument("cap2")
    folder = tmp_path / "s"
    n_darks = len(list((tmp_path / "ref" / "raw").glob("dark_*")))
    res = run(inst, folder, camera=InterruptingCamera(inst.url("camera"), n_darks + 4))
    assert not res.complete and "Ctrl-C" in res.stopped and 0 < res.n_done < len(SMALL)
    assert_clean(folder)
    res2 = resume(folder, camera=inst.url("camera"), sleep=inst.clock.advance, progress=False)
    assert res2.complete and res2.n_new == len(SMALL) - res.n_done
    a = {r["idx"]: r for r in Journal(tmp_path / "ref" / "journal.sqlite").points()}
    b = {r["idx"]: r for r in Journal(folder / "journal.sqlite").points()}
    assert sorted(b) == list(range(len(SMALL)))                   # every planned point exactly once
    for i in a:                                                   # same values as the uninterrupted run
        fa, fb = np.array(a[i]["brdf"]), np.array(b[i]["brdf"])
        s = np.hypot(a[i]["brdf_std"], b[i]["brdf_std"])
        assert np.all(np.abs(fa - fb) < 4 * s)
    assert_clean(folder)


def test_power_cycle_stops_and_resume_rehomes(instrument, tmp_path):
    inst = instrument("cap3", faults=[{"kind": "power_cycle", "port": "zaber", "at_command": 40, "device": 1}])
    folder = tmp_path / "s"
    with pytest.raises(GonioError) as e:
        run(inst, folder)
    assert "\n" not in str(e.value)
    n = len(Journal(folder / "journal.sqlite").done())
    assert n < len(SMALL)
    res = resume(folder, sleep=inst.clock.advance, progress=False)
    assert res.complete
    kinds = [k for _, k, _ in Journal(folder / "journal.sqlite").events()]
    assert "home" in kinds and "stop" in kinds
    c2, _ = chi2(folder, inst)
    assert c2 < 3.0


@pytest.mark.parametrize("fault", [
    {"kind": "garble", "port": "zaber", "probability": 0.03},
    {"kind": "timeout", "port": "zaber", "probability": 0.03},
    {"kind": "bad_checksum", "port": "zaber", "probability": 0.03},
    {"kind": "truncate", "port": "meter", "probability": 0.05},
    {"kind": "camera_truncated", "port": "camera", "at_command": [20, 30]},
    {"kind": "camera_nothing", "port": "camera", "at_command": [25]},
    {"kind": "timeout", "port": "camera", "at_command": [22]},
    {"kind": "silence", "port": "meter", "at_command": [30], "duration": 3.0},
    {"kind": "again", "port": "zaber", "probability": 0.03},
    {"kind": "limit", "port": "zaber", "at_command": [70]},
])
def test_faults_complete_with_no_wrong_point(instrument, tmp_path, fault):
    inst = instrument("f", faults=[fault])
    folder = tmp_path / "s"
    res = run(inst, folder)
    assert res.complete
    c2, rows = chi2(folder, inst)
    assert c2 < 3.0 and len(rows) == len(SMALL)
    assert_clean(folder)
    comm = [json.loads(t) for _, k, t in Journal(folder / "journal.sqlite").events() if k == "comm"][-1]
    if fault["kind"] == "limit":
        assert any("move fell short" in t and "WL" in t for _, k, t in Journal(folder / "journal.sqlite").events())
    else:
        assert comm[f"{fault['port']}_retries"] > 0            # the fault did fire and was recovered


def test_meter_vanishing_pauses_then_goes_on(instrument, tmp_path):
    inst = instrument("van", faults=[{"kind": "vanish", "port": "meter", "at_command": 30, "duration": 30.0}])
    folder = tmp_path / "s"
    res = run(inst, folder)
    assert res.complete
    events = Journal(folder / "journal.sqlite").events()
    kinds = [k for _, k, _ in events]
    assert "pause" in kinds and "resume" in kinds
    assert any("power meter is silent" in t for _, k, t in events if k == "pause")
    c2, _ = chi2(folder, inst)
    assert c2 < 3.0


def test_stage_port_vanishing_stops_resumably(instrument, tmp_path):
    inst = instrument("vz", faults=[{"kind": "vanish", "port": "zaber", "at_command": 60, "duration": 1000.0}])
    folder = tmp_path / "s"
    with pytest.raises(CommunicationError) as e:
        run(inst, folder)
    assert "reconnect" in str(e.value) and "resume" in str(e.value) and "\n" not in str(e.value)
    inst.clock.advance(1000.0)
    assert resume(folder, sleep=inst.clock.advance, progress=False).complete


def test_ctrl_c_twice_stops_the_stages(instrument, tmp_path):
    from gonio.bench.session.capture import CaptureInterrupted
    inst = instrument("cc")

    with pytest.raises(CaptureInterrupted, match="resumable"):        # Ctrl-C twice: stop now
        run(inst, tmp_path / "s", camera=InterruptingCamera(inst.url("camera"), 16, presses=2))
    assert any(k == "stop" for _, k, _ in Journal(tmp_path / "s" / "journal.sqlite").events())
    assert resume(tmp_path / "s", camera=inst.url("camera"), sleep=inst.clock.advance, progress=False).complete


def test_stall_stops_resumably_and_resume_finishes(instrument, tmp_path):
    inst = instrument("stall", faults=[{"kind": "stall", "port": "zaber", "at_command": [70]}])
    folder = tmp_path / "s"
    with pytest.raises(GonioError) as e:
        run(inst, folder)
    assert "FS stalled and stopped" in str(e.value) and "\n" not in str(e.value)
    assert resume(folder, sleep=inst.clock.advance, progress=False).complete
    c2, rows = chi2(folder, inst)
    assert c2 < 3.0 and len(rows) == len(SMALL)


def test_lamp_dies_pauses_then_stops_resumably(instrument, tmp_path):
    inst = instrument("lamp", faults=[{"kind": "lamp_dies", "port": "meter", "at_command": 25}])
    folder = tmp_path / "s"
    with pytest.raises(DeviceError) as e:
        run(inst, folder)
    msg = str(e.value)
    assert "paused" in msg and "lamp" in msg and "resume" in msg and "\n" not in msg
    kinds = [k for _, k, _ in Journal(folder / "journal.sqlite").events()]
    assert "pause" in kinds
    assert len(Journal(folder / "journal.sqlite").done()) < len(SMALL)


class CameraWithoutFlat:
    def __init__(self, url):
        self.cam = SimCamera(url)

    def expose(self, seconds, path):
        return self.cam.expose(seconds, path)

    def close(self):
        self.cam.close()


def test_flat_field_taken_once_per_session(instrument, tmp_path):
    inst = instrument("flat")
    run(inst, tmp_path / "a", plans.Plan("two", [[30, 0, 40, 180], [20, 0, 50, 90]]))
    with Journal(tmp_path / "a" / "journal.sqlite") as j:
        flats = j.frames("flat")
        assert len(flats) == S["capture"]["flat_frames"] and len({v[0] for v in flats.values()}) == 1
    assert not list((tmp_path / "a" / "raw").glob(".tmp-*"))
    # a camera without a flat source: the session says so, and a resume keeps it that way
    res = run(inst, tmp_path / "b", plans.Plan("two", [[30, 0, 40, 180], [20, 0, 50, 90]]),
              camera=CameraWithoutFlat(inst.url("camera")))
    assert res.complete
    with Journal(tmp_path / "b" / "journal.sqlite") as j:
        assert j.frames("flat") == {} and j.first_event("no_flat") is not None


class CameraDyingInTheFlats(SimCamera):
    """The simulated camera, which fails at its ``at``-th flat-field frame."""

    def __init__(self, url, at):
        super().__init__(url)
        self.at, self.flats = at, 0

    def flat_deferred(self, seconds, path):
        self.flats += 1
        if self.flats == self.at:
            raise DeviceError("the camera died in the flat field")
        return super().flat_deferred(seconds, path)


def test_flat_set_is_journalled_whole_or_not_at_all(instrument, tmp_path):
    """The flat field is one unit (gonio/bench/session/calframes.CalibrationFrames._take_flat_set): a run that dies in its middle
    journals none of it; the resume takes the set again whole, under new names, and every file
    in raw/ is one the journal reserved (the first try's frames included)."""
    inst = instrument("flatset")
    folder = tmp_path / "s"
    n = S["capture"]["flat_frames"]
    with pytest.raises(DeviceError, match="died in the flat field"):
        run(inst, folder, camera=CameraDyingInTheFlats(inst.url("camera"), at=n // 2))
    with Journal(folder / "journal.sqlite") as j:
        assert j.frames("flat") == {} and j.done() == set()
        first = {f for f in j.reserved() if "/flat_" in f}
    assert len(first) == n                                     # the whole set was reserved at once
    assert sum((folder / f).stat().st_size > 0 for f in first) == n // 2 - 1    # the frames taken
    res = resume(folder, camera=inst.url("camera"), sleep=inst.clock.advance, progress=False)
    assert res.complete
    with Journal(folder / "journal.sqlite") as j:
        flats = {v[1] for v in j.frames("flat").values()}
        reserved = j.reserved()
    assert len(flats) == n and not flats & first               # taken again whole, new names
    assert {f"raw/{p.name}" for p in (folder / "raw").iterdir()} <= reserved
    for name, (t, file, digest) in Journal(folder / "journal.sqlite").frames("flat").items():
        assert sha256_file(folder / file) == digest
    assert_clean(folder)


def test_bad_inputs_leave_nothing_behind(instrument, tmp_path):
    inst = instrument("bad")
    with pytest.raises(CommunicationError, match="cannot open the stage port"):
        capture(tmp_path / "a", SMALL, S, "/dev/no-such-port", inst.url("meter"), inst.url("camera"), progress=False)
    assert not (tmp_path / "a").exists()
    with pytest.raises(CommunicationError, match="power-meter port"):
        capture(tmp_path / "a", SMALL, S, inst.url("zaber"), "sim://nobody/meter", inst.url("camera"), progress=False)
    assert not (tmp_path / "a").exists()
    bad = plans.Plan("bad", [[30, 0, 40, 180], [30, 0, 30, 0]])
    with pytest.raises(UnreachableError, match="1 unreachable"):
        run(inst, tmp_path / "b", bad)
    assert not (tmp_path / "b").exists()
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "x").write_text("")
    with pytest.raises(SessionError, match="not empty"):
        run(inst, tmp_path / "c")
    with pytest.raises(SessionError, match="not a gonio session"):
        resume(tmp_path / "c")


def test_reference_model():
    from gonio.bench.measure.point import ReferenceModel
    flat = ReferenceModel({"reflectance": 0.99})
    np.testing.assert_allclose(flat.f_r(30, 40), np.full(3, 0.99 / np.pi))
    m = ReferenceModel({"reflectance": [0.98, 0.99, 0.97], "factor_theta_i": [0, 60], "factor_theta_o": [0, 80],
                        "factor": [[1.0, 0.9], [1.1, 0.95]]})
    assert m.factor(0, 0) == 1.0 and m.factor(60, 80) == 0.95 and m.factor(30, 40) == pytest.approx((1 + 0.9 + 1.1 + 0.95) / 4)
    assert m.factor(90, 90) == 0.95                                    # clamped at the table's edge
    np.testing.assert_allclose(m.f_r(0, 0), np.array([0.98, 0.99, 0.97]) / np.pi)
    with pytest.raises(GonioError, match="factor"):
        ReferenceModel({"reflectance": 0.99, "factor_theta_i": [0], "factor_theta_o": [0, 1], "factor": [[1.0]]})


def test_reference_model_uses_the_calibrations_fitted_form():
    """With gonio calibrate's fit (factor_a, factor_b) the factor is the fitted form itself
    (gonio/bench/measure/alignment.reference_factor_model), not the bilinear interpolation of its 20-degree
    table, which overstates the convex sin^2 between the nodes: for a = 0.05, b = 0.06 (the
    simulator's Spectralon, gonio/sim/physics/errors.spectralon_factor) the table is 2.9e-4 low at 30/30 deg
    and exact at its nodes."""
    from gonio.bench.measure.alignment import fit_reference_factor, reference_factor_model
    from gonio.bench.measure.point import ReferenceModel
    a, b = 0.05, 0.06
    g = np.array([10.0, 25.0, 40.0, 55.0, 70.0])
    ti, to = (v.ravel() for v in np.meshgrid(g, g, indexing="ij"))
    fit = fit_reference_factor(ti, to, reference_factor_model(ti, to, a, b), np.full(ti.size, 1e-4))
    ref = {"reflectance": 0.99, "factor_theta_i": fit["grid_deg"], "factor_theta_o": fit["grid_deg"],
           "factor": fit["factor"]}
    table_only = ReferenceModel(ref)
    fitted = ReferenceModel({**ref, "factor_a": fit["a"], "factor_b": fit["b"]})
    exact = float(reference_factor_model(30.0, 30.0, a, b))
    assert fitted.factor(30.0, 30.0) == pytest.approx(exact, abs=1e-9)
    assert table_only.factor(30.0, 30.0) - exact < -2.5e-4        # the interpolation's one-signed error
    assert fitted.factor(40.0, 60.0) == pytest.approx(table_only.factor(40.0, 60.0), abs=1e-9)   # at a node
    with pytest.raises(GonioError, match="factor_a and factor_b"):
        ReferenceModel({**ref, "factor_a": 0.05})


def test_camera_size_must_match_settings(instrument, tmp_path):
    from gonio.bench.settings import merge_settings
    inst = instrument("size")
    wrong = merge_settings(S, {"camera": {"width": 128}})
    with pytest.raises(GonioError, match="camera reports 64x48 pixels"):
        capture(tmp_path / "s", SMALL, wrong, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                progress=False, sleep=inst.clock.advance)
    assert not (tmp_path / "s").exists()


def test_no_flat_frames_wanted_with_a_flat_source(instrument, tmp_path):
    """``[capture] flat_frames = 0`` with a camera that has a flat source: no flat field, said once
    (it ended in StopIteration in _take_flats), and a resume keeps it that way."""
    inst = instrument("noflat")
    settings = {**S, "capture": {**S["capture"], "flat_frames": 0}}
    plan = plans.Plan("two", [[30, 0, 40, 180], [20, 0, 50, 90]])
    res = capture(tmp_path / "s", plan, settings, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                  seed=inst.seed, progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec)
    assert res.complete and res.n_new == 2
    with Journal(tmp_path / "s" / "journal.sqlite") as j:
        assert j.frames("flat") == {} and j.first_event("no_flat") is not None
    res = resume(tmp_path / "s", progress=False, sleep=inst.clock.advance, remeasure="1")
    assert res.complete and res.n_new == 1
    assert_clean(tmp_path / "s")


def test_windowed_decode_is_the_crop_of_the_full_decode(instrument, tmp_path):
    """What a point decodes (the regions' box, from bytes already read, darks without peaks) is
    exactly the crop of the full frame."""
    from gonio.bench.drivers.camera import decode_raw, read_verified

    inst = instrument("window")
    path = tmp_path / "f.dng"
    path.write_bytes(inst.capture(0.01))
    full = decode_raw(path)
    data, digest = read_verified(path)
    assert digest == sha256_file(path)
    h, w = full.signal.shape[1:]
    for box in ((0, h, 0, w), (3, h - 5, 7, w - 2), (h // 2, h // 2 + 1, 0, 1)):
        part = decode_raw(path, window=box, data=data)
        win = np.s_[:, box[0]:box[1], box[2]:box[3]]
        assert np.array_equal(part.signal, full.signal[win]) and np.array_equal(part.peak, full.peak[win])
        assert part.signal.dtype == np.float32 and (part.black, part.white) == (full.black, full.white)
    dark = decode_raw(path, peak=False)
    assert dark.peak is None and np.array_equal(dark.signal, full.signal)
    # float32 holds the raw values exactly: the greens' mean is a half-integer at most
    assert np.array_equal(full.signal * 2, np.round(full.signal * 2))


def test_a_simple_dng_is_read_directly_bit_for_bit(instrument, tmp_path, monkeypatch):
    """A point's frames need no colour matrix (``colour=False``): an uncompressed one-image DNG,
    the simulated camera's, is then read straight from its bytes, inside the box only, instead of
    LibRaw unpacking the whole sensor; every value is LibRaw's, bit for bit. Anything else
    (here an active area, a truncated file) is left to LibRaw, as before."""
    import tifffile

    from gonio.bench.drivers.camera import _dng_direct, decode_raw
    from gonio.sim.physics.sensor import encode_dng

    from gonio.bench.drivers import raw as _raw

    monkeypatch.setattr(_raw, "_DIRECT_MIN_BYTES", 0)     # the default camera's frames are small
    inst = instrument("direct")
    for t in (0.0005, 0.01, 0.2):                       # dim, mid, saturated in places
        data = inst.capture(t)
        assert _dng_direct(data) is not None
        full = decode_raw(tmp_path / "x.dng", data=data)
        h, w = full.signal.shape[1:]
        for box in (None, (3, h - 5, 7, w - 2), (h // 2, h // 2 + 1, 0, 1), (-4, h + 9, -1, 3), (5, 5, 0, w)):
            for peak in (True, False):
                want = decode_raw(tmp_path / "x.dng", window=box, data=data, peak=peak)
                got = decode_raw(tmp_path / "x.dng", window=box, data=data, peak=peak, colour=False)
                assert np.array_equal(got.signal, want.signal) and got.signal.dtype == np.float32
                assert (got.peak is None) == (want.peak is None)
                assert got.peak is None or np.array_equal(got.peak, want.peak)
                assert np.array_equal(got.n_raw, want.n_raw) and (got.black, got.white) == (want.black, want.white)
                assert got.rgb_cam is None
    (tmp_path / "f.dng").write_bytes(data)              # from the file when no bytes are given
    assert np.array_equal(decode_raw(tmp_path / "f.dng", colour=False).signal, full.signal)
    # not read directly: LibRaw decodes (an active area), or refuses (a truncated file)
    raw = np.arange(16 * 24, dtype=np.uint16).reshape(16, 24) + 600
    plain = encode_dng(raw, black=512, white=16383)
    buf = __import__("io").BytesIO()
    tifffile.imwrite(buf, raw, photometric=32803, metadata=None, extratags=[
        (50706, "B", 4, (1, 4, 0, 0), True), (33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
        (50714, "I", 1, (512,), True), (50717, "I", 1, (16383,), True), (50829, "I", 4, (2, 2, 16, 24), True)])
    for other in (buf.getvalue(), plain[: len(plain) // 2]):
        assert _dng_direct(other) is None
    with pytest.raises(GonioError, match="cannot decode"):
        decode_raw(tmp_path / "t.dng", data=plain[: len(plain) // 2], colour=False)


def test_the_direct_probe_chooses_libraws_bracket(instrument, tmp_path, monkeypatch):
    """The bracket a point's probe picks, read directly (what the capture does now) and through
    LibRaw (what it did), on the poses of a shiny sample's capture: the same at every pose."""
    from gonio.bench.measure.hdr import NoiseModel, choose_bracket, ladder
    from gonio.bench.measure.point import _extreme, _runs
    from gonio.bench.session.run import roi_masks_fast
    from gonio.bench.drivers import raw as _raw
    from gonio.bench.drivers.camera import decode_raw

    monkeypatch.setattr(_raw, "_DIRECT_MIN_BYTES", 0)     # read directly whatever the size
    inst = instrument("probe", sample={"model": "roughplastic",
                                        "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.03}})
    folder = tmp_path / "s"
    assert run(inst, folder).complete
    cap = S["capture"]
    rungs = ladder(float(cap["exposure_min_s"]), float(cap["exposure_max_s"]))
    noise = NoiseModel(float(S["camera"].get("gain_e_per_dn", 2.0)), float(S["camera"].get("read_noise_e", 3.0)))
    sat = float(cap["saturation_fraction"])
    darks = {f.name: f for f in (folder / "raw").iterdir() if f.name.startswith("dark_")}
    chosen = []
    for r in Journal(folder / "journal.sqlite").points():
        sm, rm = roi_masks_fast(np.array([r["yaw"], r["tilt"], r["azimuth"], r["lamp"]]), S)
        both = sm | rm
        rows, cols = np.flatnonzero(both.any(1)), np.flatnonzero(both.any(0))
        box = (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)
        runs = _runs(both[box[0]:box[1], box[2]:box[3]])
        for e in r["detail"]["exposures"]:                 # each frame as if it were the probe
            t = e["seconds"]
            dk = decode_raw(darks[f"dark_{t * 1e6:010.0f}us.dng"], window=box, peak=False).signal
            picks = []
            for colour in (True, False):
                f = decode_raw(folder / e["file"], window=box, colour=colour)
                peak = _extreme(np.maximum, f.peak - np.maximum(dk, 0), runs)
                low = _extreme(np.minimum, f.signal - dk, runs)
                picks.append(choose_bracket(rungs, t, peak, low, f.full_scale, noise, sat, float(cap["noise_floor_snr"])))
            assert picks[0] == picks[1], (r["idx"], t, picks)
            chosen.append(tuple(picks[0]))
    assert len(set(chosen)) > 2                          # the poses ask for different brackets


@pytest.mark.slow  # 40 s at load 4-5 (a capture with the holder scene rendered): run early (tests/conftest.py)
def test_regions_from_the_holders_markers(tmp_path):
    """Settings that declare holder markers: each point's regions come from the markers in its
    probe (the pose is journalled), so a holder moved by a known offset is measured where it is."""
    from gonio.bench.plan import markers as _markers
    from gonio.bench.settings import merge_settings

    bench = merge_settings(default_settings(), {"camera": {"width": 480, "height": 360, "pixel_size": 0.0027}})
    bench["holder"] = {**bench["holder"], "markers": _markers.example_layout()}
    shift, turn = (0.04, -0.03), 3.0
    simset = {**bench, "holder": {**bench["holder"], "sim_pose": [*shift, turn]}}
    inst = sim.Instrument(simset, sample=GLOSSY, seed=2).register("markers")
    try:
        plan = plans.Plan("two", [[30, 0, 40, 180], [20, 0, 50, 90]])
        res = capture(tmp_path / "s", plan, bench, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                      seed=2, progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec)
        assert res.complete
        rows = Journal(tmp_path / "s" / "journal.sqlite").points()
        for r in rows:
            reg = r["detail"]["regions"]
            assert reg["source"] == "markers", reg["why"]
            assert np.allclose(reg["shift_m"], shift, atol=2 * bench["camera"]["pixel_size"])
            assert reg["angle_deg"] == pytest.approx(turn, abs=0.5)
        wi = np.array([kinematics.directions(r["theta_i"], r["phi_i"]) for r in rows])
        wo = np.array([kinematics.directions(r["theta_o"], r["phi_o"]) for r in rows])
        f, s = np.array([r["brdf"] for r in rows]), np.array([r["brdf_std"] for r in rows])
        truth = inst.true_brdf(wi, wo) @ inst.sensor.colour.balanced.T      # in camera RGB, as journalled
        assert np.mean(((f - truth) / s) ** 2) < 5.0
    finally:
        inst.unregister()
    # without markers in the settings the geometry's regions are used and nothing is journalled about them
    inst = sim.Instrument(S, sample=GLOSSY, seed=2).register("nomarkers")
    try:
        run(inst, tmp_path / "g", plans.Plan("one", [[30, 0, 40, 180]]))
        assert "regions" not in Journal(tmp_path / "g" / "journal.sqlite").points()[0]["detail"]
    finally:
        inst.unregister()


def test_fast_roi_masks_are_the_geometry_masks_exactly():
    """The capture's regions (`roi_masks_fast`: `_markers.posed_masks` with the ties on a square's
    edge decided by `kinematics.roi_masks`' own test) are `roi_masks`' masks, pixel for pixel, on
    the plan's poses and on random ones (posed_masks alone differs at ties on the default camera)."""
    from gonio.bench.settings import merge_settings
    from gonio.bench.session.run import roi_masks_fast

    rng = np.random.default_rng(7)
    for w, h in ((64, 48), (320, 240)):
        px = float(S["camera"]["pixel_size"]) * S["camera"]["width"] / w
        s = merge_settings(S, {"camera": {"width": w, "height": h, "pixel_size": px}})
        stages = list(plans.require_reachable(plans.load_plan("quick"), s))
        stages += [np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-180, 180), rng.uniform(10, 170)])
                   for _ in range(10)]
        for stage in stages:
            want, got = kinematics.roi_masks(stage, s), roi_masks_fast(stage, s)
            assert all(np.array_equal(a, b) for a, b in zip(want, got)), (w, stage)
            # the lamp's angle moves no region: the capture caches the masks per holder pose
            lamp = roi_masks_fast(np.array([*stage[:3], (stage[3] + 37.0) % 180]), s)
            assert all(np.array_equal(a, b) for a, b in zip(lamp, got))
