"""Zemax tabular BSDF read and write (gonio.fitting.formats.zemax; issue 37).

The shared example (../shared/data/zemax, an FDTD grating's BTDF at 550 nm converted from
Speos) is read and its geometry checked against the format's definition (radial angles about
the specular direction, azimuth 0 toward the normal: a row at azimuth 0 reaches the horizon at
radial 90 + AOI, at 180 deg at 90 - AOI); a model's table survives write -> read with every
angle and value; malformed files give one line naming the file and the line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting.formats.zemax import (MAX_VALUES, ZemaxError, export_zemax, is_zemax_bsdf, model_zemax,
                                         read_zemax, write_zemax, zemax_directions, zemax_measurements)

EXAMPLE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "zemax" / "fdtd_grating_btdf_550nm_zemax.bsdf"
RGL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "rgl" / "paper_white_rgb.bsdf"

needs_example = pytest.mark.skipif(not EXAMPLE.is_file(), reason="../shared/data/zemax example absent")


@needs_example
def test_reads_the_shared_example():
    assert is_zemax_bsdf(EXAMPLE)
    z = read_zemax(EXAMPLE)
    assert (z.scatter_type, z.symmetry, z.spectral, z.source) == ("BTDF", "Asymmetrical", "Monochrome", "Measured")
    assert z.channels == ("550nm",) and z.wavelength_nm == 550.0
    np.testing.assert_array_equal(z.rotation, [0.0])
    np.testing.assert_array_equal(z.aoi, [0.0, 22.5, 45.0, 67.5])
    np.testing.assert_array_equal(z.azimuth, np.arange(361.0))
    np.testing.assert_array_equal(z.radial, np.arange(181.0))
    np.testing.assert_array_equal(z.tis.ravel(), [0.043, 0.051, 0.056, 0.009])
    assert z.data.shape == (1, 1, 4, 361, 181)
    assert z.data[0, 0, 0, 0, 0] == 1.227e-01 and z.data[0, 0, 3, -1, 9] == 2.887e-04   # first and last rows
    # the table is zero beyond the horizon exactly where the geometry puts it
    for a, aoi in enumerate(z.aoi):
        for k, limit in ((0, 90.0 + aoi), (180, 90.0 - aoi), (90, 90.0)):
            last = z.radial[np.nonzero(z.data[0, 0, a, k])[0].max()]
            assert limit - 1.0 <= last <= limit, (aoi, k, last)
    m = zemax_measurements(EXAMPLE)
    assert m.channels == ("550nm",) and m.attrs["sides"] == ["transmit"] and m.attrs["scatter_type"] == "BTDF"
    assert np.all(m.wo[:, 2] < 0) and np.all(m.wi[:, 2] >= 0) and np.all(m.brdf >= 0)
    wi, wo = zemax_directions("BTDF", z.rotation, z.aoi, z.azimuth, z.radial)
    assert m.n_points == int((wo[..., 2] < -1e-9).sum())
    assert m.attrs["off_side_nonzero"] < 1e-2 * m.n_points          # cells straddling the horizon
    assert zemax_measurements(EXAMPLE, as_rgb=True).channels == ("R", "G", "B")


@needs_example
def test_example_round_trip_keeps_every_angle_and_value(tmp_path):
    z = read_zemax(EXAMPLE)
    out = tmp_path / "copy.txt"
    assert write_zemax({out: z}) == [out]
    back = read_zemax(out)
    for what in ("rotation", "aoi", "azimuth", "radial", "tis", "data"):
        np.testing.assert_array_equal(getattr(back, what), getattr(z, what))
    assert back.comments == z.comments


def test_not_zemax_by_content(tmp_path):
    if RGL.is_file():
        assert not is_zemax_bsdf(RGL)
        with pytest.raises(ZemaxError, match="not a Zemax tabular BSDF"):
            read_zemax(RGL)
    (tmp_path / "a.bsdf").write_bytes(b"tensor_file\x00\x01\x00junk")
    (tmp_path / "b.bsdf").write_text("hello\nworld\n")
    (tmp_path / "c.txt").write_text("# comment\nSource Measured\nSymmetry Asymmetrical\nSpectralContent Monochrome\n"
                                    "ScatterType BRDF\n")
    assert not is_zemax_bsdf(tmp_path / "a.bsdf") and not is_zemax_bsdf(tmp_path / "b.bsdf")
    assert is_zemax_bsdf(tmp_path / "c.txt")            # the extension does not matter
    assert not is_zemax_bsdf(tmp_path / "missing.bsdf")


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_model_round_trip_both_sides(tmp_path, distribution):
    """A frosted glass written on both sides, read back: every angle and value as tabulated,
    and the measurements read from the files are the model's f_r at their directions."""
    model = gm.get("roughdielectric", distribution=distribution)
    p = {"alpha": 0.3, "int_ior": 1.5}
    grid = {"aoi": np.arange(0.0, 90.0, 10.0), "azimuth": np.arange(0.0, 360.0, 10.0), "radial": np.arange(0.0, 181.0, 3.0)}
    paths = export_zemax(tmp_path / "frosted", model, p, **grid)
    assert [q.name for q in paths] == ["frosted_brdf.bsdf", "frosted_btdf.bsdf"]
    for q, kind in zip(paths, ("BRDF", "BTDF")):
        want = model_zemax(model, p, kind, **grid)
        got = read_zemax(q)
        assert got.scatter_type == kind and got.comments[0].startswith(f"gonio model roughdielectric(distribution={distribution})")
        for what in ("aoi", "azimuth", "radial", "tis", "data"):
            np.testing.assert_array_equal(getattr(got, what), getattr(want, what))
        m = zemax_measurements(q)
        f = model.eval(m.wi, m.wo, p)[:, 0]
        np.testing.assert_allclose(m.brdf[:, 0], f, rtol=1e-15, atol=0)      # luminance of equal channels
        assert np.all((m.wo[:, 2] < 0) == (kind == "BTDF"))
        wi, wo = zemax_directions(kind, [0.0], grid["aoi"], grid["azimuth"], grid["radial"])
        assert m.n_points == int(got.side.mask(wi[..., 2], wo[..., 2], 1e-9).sum())
    # TIS is R and T of the grid: close to the model's own integrals at normal incidence
    from gonio.models.catalogue.roughdielectric import reflectance_transmittance
    R, T = reflectance_transmittance(distribution, 0.3, 1.5, np.array([[0.0, 0.0, 1.0]]))
    assert read_zemax(paths[0]).tis[0, 0, 0] == pytest.approx(R[0], rel=0.05)
    assert read_zemax(paths[1]).tis[0, 0, 0] == pytest.approx(T[0], rel=0.02)


def test_reflection_model_writes_one_file_and_xyz(tmp_path):
    model = gm.get("roughconductor", distribution="ggx")
    p = {"eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2], "alpha": 0.2}
    paths = export_zemax(tmp_path / "metal", model, p, aoi=[0.0, 45.0], azimuth=np.arange(0.0, 360.0, 30.0),
                         radial=np.arange(0.0, 181.0, 10.0))
    assert [q.name for q in paths] == ["metal_brdf.bsdf"]
    t = model_zemax(model, p, "BRDF", aoi=[0.0, 45.0], azimuth=[0.0, 90.0], radial=[0.0, 10.0], spectral="XYZ")
    out = tmp_path / "xyz.bsdf"
    write_zemax({out: t})
    z = read_zemax(out)
    assert z.channels == ("X", "Y", "Z") and z.data.shape == (3, 1, 2, 2, 2)
    np.testing.assert_array_equal(z.data, t.data)


# -- malformed files ------------------------------------------------------------------------------

SMALL = """# a small table
Source  Measured
Symmetry  PlaneSymmetrical
SpectralContent  Monochrome
ScatterType  BRDF
SampleRotation  1
0
AngleOfIncidence  2
0 30
ScatterAzimuth 3
0 90 180
ScatterRadial 4
0 10 20 30

Monochrome
DataBegin
TIS 0.5
1 2 3 4
1 2 3 4
1 2 3 4
TIS 0.4
1 2 3 4
1 2 3 4
1 2 3 4
DataEnd
"""


def _edit(text, old, new, count=1):
    assert old in text
    return text.replace(old, new, count)


MALFORMED = {
    "truncated": (lambda t: t[: t.index("TIS 0.4")] + "TIS 0.4\n1 2 3 4\n", "truncated"),
    "cut mid-row": (lambda t: t[: t.index("TIS 0.4") + 14], "3 values where"),
    "truncated header": (lambda t: t[: t.index("ScatterAzimuth")], "truncated"),
    "bad number": (lambda t: _edit(t, "1 2 3 4\n1 2 3 4\nTIS", "1 2 x3 4\n1 2 3 4\nTIS"), "'x3' is not a number"),
    "nan": (lambda t: _edit(t, "1 2 3 4", "1 nan 3 4"), "'nan' is not a number"),
    "inf": (lambda t: _edit(t, "1 2 3 4", "1 2 inf 4"), "'inf' is not a number"),
    "overflow": (lambda t: _edit(t, "1 2 3 4", "1 2 1e999 4"), "not finite"),
    "huge value": (lambda t: _edit(t, "1 2 3 4", "1 2 3e12 4"), "outside"),
    "negative value": (lambda t: _edit(t, "1 2 3 4", "1 -2 3 4"), "outside"),
    "short row": (lambda t: _edit(t, "1 2 3 4", "1 2 3"), "3 values where"),
    "too many rows": (lambda t: _edit(t, "1 2 3 4\nTIS 0.4", "1 2 3 4\n1 2 3 4\nTIS 0.4"), "where 'TIS value'"),
    "too few rows": (lambda t: _edit(t, "1 2 3 4\nDataEnd", "DataEnd"), "'DataEnd' is not a number"),
    "count mismatch": (lambda t: _edit(t, "ScatterRadial 4", "ScatterRadial 5"), "4 values where ScatterRadial needs 5"),
    "huge count": (lambda t: _edit(t, "AngleOfIncidence  2", "AngleOfIncidence  100000"), "outside 1..900"),
    "too many values": (lambda t: _edit(_edit(_edit(t, "ScatterRadial 4\n0 10 20 30", "ScatterRadial 1801\n"
                                                    + " ".join(str(x / 10) for x in range(1801))),
                                              "ScatterAzimuth 3\n0 90 180", "ScatterAzimuth 1801\n"
                                              + " ".join(str(x / 10) for x in range(1801))),
                                        "AngleOfIncidence  2\n0 30", "AngleOfIncidence  6\n0 10 20 30 40 50"),
                        "more than"),
    "zero count": (lambda t: _edit(t, "SampleRotation  1", "SampleRotation  0"), "outside 1..360"),
    "angle range": (lambda t: _edit(t, "0 90 180\n", "0 90 200\n"), "must lie in"),
    "not increasing": (lambda t: _edit(t, "0 10 20 30", "0 20 10 30"), "strictly increasing"),
    "incidence 90": (lambda t: _edit(t, "0 30\n", "0 90\n"), "must lie in"),
    "bad tis": (lambda t: _edit(t, "TIS 0.5", "TIS 7"), "outside [0, 2]"),
    "nan tis": (lambda t: _edit(t, "TIS 0.5", "TIS nan"), "not a number"),
    "no tis": (lambda t: _edit(t, "TIS 0.5\n", ""), "where 'TIS value'"),
    "unknown symmetry": (lambda t: _edit(t, "PlaneSymmetrical", "Round"), "Symmetry 'Round' is not one of"),
    "4d": (lambda t: _edit(t, "PlaneSymmetrical", "Asymmetrical4D"), "Asymmetrical4D is not read"),
    "header order": (lambda t: _edit(t, "ScatterAzimuth 3", "ScatterAzimut 3"), "where the header line 'ScatterAzimuth'"),
    "no databegin": (lambda t: _edit(t, "DataBegin", "Begin"), "where DataBegin belongs"),
    "wrong block": (lambda t: _edit(t, "Monochrome\nDataBegin", "TristimulusX\nDataBegin"), "where the data block"),
    "junk after": (lambda t: t + "leftover 1 2\n", "after the last DataEnd"),
    "no dataend": (lambda t: _edit(t, "DataEnd\n", ""), "truncated"),
    "binary": (lambda t: "Source Measured\x00\x01\x02", "not a Zemax tabular BSDF"),
    "empty": (lambda t: "", "not a Zemax tabular BSDF"),
}


def test_the_small_table_reads(tmp_path):
    (tmp_path / "s.bsdf").write_text(SMALL)
    z = read_zemax(tmp_path / "s.bsdf")
    assert z.data.shape == (1, 1, 2, 3, 4) and z.symmetry == "PlaneSymmetrical"
    m = zemax_measurements(tmp_path / "s.bsdf")
    assert m.channels == ("Y",) and np.all(m.wo[:, 2] > 0)


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_files_give_one_line(tmp_path, case):
    edit, message = MALFORMED[case]
    path = tmp_path / "bad.bsdf"
    path.write_text(edit(SMALL), encoding="latin-1")
    with pytest.raises(ZemaxError) as info:
        read_zemax(path)
    text = str(info.value)
    assert "\n" not in text and str(path) in text and len(text) < 400, text
    assert message in text, text


def test_files_that_are_not_files(tmp_path):
    with pytest.raises(ZemaxError, match="does not exist"):
        read_zemax(tmp_path / "missing.bsdf")
    with pytest.raises(ZemaxError, match="is a folder"):
        read_zemax(tmp_path)


def test_writer_refuses_values_it_cannot_write(tmp_path):
    t = model_zemax(gm.get("diffuse"), {}, "BRDF", aoi=[0.0], azimuth=[0.0], radial=[0.0])
    t.data[...] = np.nan
    with pytest.raises(ZemaxError, match="non-finite"):
        write_zemax({tmp_path / "x.bsdf": t})
    assert not (tmp_path / "x.bsdf").exists()
    assert MAX_VALUES >= 4 * 361 * 181
