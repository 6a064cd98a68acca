"""A fit written as an RGL-EPFL ``.bsdf`` file on the grid of the RGL file it was fitted to.

The file keeps the source's incidences and warps (NDF, projected area, VNDF and luminance
tables) and holds the fit's values where the source holds the measured ones, so Mitsuba's
``measured`` plugin reads and samples it exactly as it does the measurement. Rendered beside
the source with the same seed, both draw the same directions from the same random numbers:
their difference is the fit's, not two plugins' sampling noise. Format: Dupuy & Jakob 2018
(ACM TOG 37(6), the RGL adaptive parameterisation), as Mitsuba 3's ``TensorFile`` and
``measured`` plugin read it.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from gonio.fitting.formats import _TENSOR_DTYPES as _CODES, check_rgl_file
from gonio.fitting.formats.readback import expect, written
from gonio.models.mitsuba import select_variant

__all__ = ["read_tensor", "tensor_bytes", "write_tensor", "grid_directions", "fit_on_rgl_grid", "grid_error", "check_grid", "MAX_NODES"]

_DTYPE_CODE = {np.dtype(v).str: k for k, v in _CODES.items()}
#: field data starts on this boundary (the plugin reads float32 tables in place)
_ALIGN = 8
#: the most value nodes (phi_i x theta_i x H x W) gonio writes on: RGL's files have 8 x 32 x 32
MAX_NODES = 1 << 21


def read_tensor(path) -> dict:
    """Every field of a checked RGL ``.bsdf`` tensor file (:func:`check_rgl_file`), in file
    order, as numpy arrays of the stored dtype."""
    fields = check_rgl_file(path)
    raw = Path(path).read_bytes()
    out = {}
    for name, (code, shape, offset) in fields.items():
        count = int(np.prod(shape, dtype=np.int64)) if shape else 1
        out[name] = np.frombuffer(raw, dtype=_CODES[code], count=count, offset=offset).reshape(shape).copy()
    return out


def tensor_bytes(fields: dict) -> bytes:
    """The tensor file holding ``fields`` (name -> array, in order): the header Mitsuba's
    ``TensorFile`` reads, then each field's data, every one aligned to 8 bytes."""
    names = list(fields)
    arrays = [np.ascontiguousarray(fields[n]) for n in names]
    for n, a in zip(names, arrays):
        if a.dtype.str not in _DTYPE_CODE and a.dtype.newbyteorder("<").str not in _DTYPE_CODE:
            raise ValueError(f"field {n!r}: dtype {a.dtype} has no tensor-file code")
    head_size = 12 + 2 + 4 + sum(2 + len(n.encode("ascii")) + 2 + 1 + 8 + 8 * a.ndim for n, a in zip(names, arrays))
    offset = -(-head_size // _ALIGN) * _ALIGN
    head = bytearray(b"tensor_file\x00" + bytes([1, 0]) + struct.pack("<I", len(names)))
    body = bytearray()
    for n, a in zip(names, arrays):
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        head += struct.pack("<H", len(n)) + n.encode("ascii")
        head += struct.pack("<HBQ", a.ndim, _DTYPE_CODE[a.dtype.str], offset + len(body))
        head += struct.pack(f"<{a.ndim}Q", *a.shape)
        body += a.tobytes()
        body += bytes(-len(body) % _ALIGN)
    head += bytes(offset - len(head))
    return bytes(head) + bytes(body)


def write_tensor(path, fields: dict, verify=None) -> Path:
    """Write ``fields`` as an RGL ``.bsdf`` tensor file, atomically: read back and compared
    field by field (name, dtype, shape, every value; NaN equal to NaN), then ``verify(tmp)``
    where given (it raises to refuse), before the file gets its name; on any failure nothing
    is left and an earlier file of that name is as it was."""
    data = tensor_bytes(fields)
    path = Path(path)

    def write(tmp):
        Path(tmp).write_bytes(data)

    def check(tmps):
        back = read_tensor(tmps[path])
        expect("tensor fields", list(fields), list(back))
        same = 0
        for n in fields:
            a = np.asarray(fields[n])
            same += bool(a.dtype.newbyteorder("<") == back[n].dtype.newbyteorder("<") and a.shape == back[n].shape
                         and np.array_equal(a, back[n], equal_nan=a.dtype.kind == "f"))
        expect("fields read back equal (dtype, shape, values)", len(fields), same)
        if verify is not None:
            verify(tmps[path])

    written({path: write}, check)
    return path


def check_grid(fields: dict) -> tuple:
    """The value table's (P, T, C, H, W) where ``fields`` hold an isotropic RGB RGL grid that
    Mitsuba's ``measured`` accepts and gonio writes on, else ValueError (one line)."""
    if "rgb" not in fields:
        raise ValueError("the RGL file is spectral (spectra, wavelengths); gonio writes RGB values on an RGB file's grid")
    rgb, vndf, lum = fields["rgb"], fields["vndf"], fields["luminance"]
    if rgb.ndim != 5 or rgb.shape[2] != 3:
        raise ValueError(f"the RGL file's value table has shape {rgb.shape}; expected (phi_i, theta_i, 3, H, W)")
    P, T, C, H, W = rgb.shape
    if P > 2:
        raise ValueError(f"the RGL file is anisotropic ({P} phi_i); gonio writes on an isotropic file's grid only")
    shapes_ok = (fields["phi_i"].shape == (P,) and fields["theta_i"].shape == (T,) and H == W and H >= 2
                 and vndf.ndim == 4 and vndf.shape[:2] == (P, T) and min(vndf.shape[2:]) >= 2
                 and lum.shape == (P, T, H, W) and all(fields[k].ndim == 2 and min(fields[k].shape) >= 2 for k in ("ndf", "sigma"))
                 and fields["jacobian"].dtype == np.uint8 and fields["jacobian"].shape == (1,))
    if not shapes_ok:
        raise ValueError("the RGL file's tables do not fit together (shapes of rgb, vndf, luminance, ndf, sigma, "
                         "theta_i, phi_i, jacobian): Mitsuba's measured plugin would refuse it")
    if P * T * H * W > MAX_NODES or vndf[0, 0].size > MAX_NODES:
        raise ValueError(f"the RGL file's grid has {P * T * H * W} value nodes; gonio writes on grids of at most {MAX_NODES}")
    theta = fields["theta_i"].astype(np.float64)
    if not (np.all(np.diff(theta) > 0) and theta[0] >= 0.0 and theta[-1] <= np.pi / 2 + 1e-6):
        raise ValueError("the RGL file's theta_i are not increasing within 0-90 deg")
    for k in ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance"):
        if not np.all(np.isfinite(fields[k])):
            raise ValueError(f"the RGL file's {k} table is not finite")
    return P, T, C, H, W


def grid_directions(fields: dict, variant: str | None = None):
    """The direction pair behind every value node of an isotropic RGB RGL file.

    Returns ``(wi, wo, factor, shape)``: for the node (phi_i p, theta_i t, row j, column k),
    flattened in (p, t, j, k) order, gonio's ``wi`` (toward the light: the direction the plugin
    samples) and ``wo`` (toward the sensor: the plugin's incident direction), and ``factor``,
    what the plugin multiplies the stored value by (NDF / (4 projected area) where the file's
    ``jacobian`` flag is set, else 1), so that a stored value of ``f_r cos(theta_wi) / factor``
    evaluates to ``f_r cos(theta_wi)``. ``shape`` is the value table's (P, T, C, H, W). The
    node's sample position is (k / (W - 1), j / (H - 1)); the VNDF warp maps it to the
    half-vector as the plugin's ``sample`` does (Mitsuba's own warp, so the mapping is the
    plugin's to float32)."""
    import mitsuba as mi

    variant = select_variant(variant)
    if not variant.startswith(("llvm", "cuda")):
        raise ValueError(f"writing on an RGL file's grid needs a vectorised Mitsuba variant, not {variant}")
    P, T, C, H, W = check_grid(fields)
    phi_i, theta_i = fields["phi_i"].astype(np.float64), fields["theta_i"].astype(np.float64)
    try:
        return _directions(mi, variant, fields, phi_i, theta_i, (P, T, C, H, W))
    except (TypeError, RuntimeError, IndexError) as exc:        # Mitsuba's warps refuse the tables
        raise ValueError(f"Mitsuba cannot build the RGL file's warps ({' '.join(str(exc).split())[:160]})") from None


def _directions(mi, variant, fields, phi_i, theta_i, shape):
    P, T, C, H, W = shape
    jacobian = bool(np.asarray(fields["jacobian"]).reshape(-1)[0])
    y, x = np.meshgrid(np.arange(H) / (H - 1), np.arange(W) / (W - 1), indexing="ij")
    n = H * W
    wis, wos, factors = [], [], []
    with mi.scoped_set_variant(variant):
        vndf = mi.MarginalContinuous2D2(np.ascontiguousarray(fields["vndf"], dtype=np.float32),
                                        [phi_i.astype(np.float32).tolist(), theta_i.astype(np.float32).tolist()])
        ndf = mi.MarginalDiscrete2D0(np.ascontiguousarray(fields["ndf"], dtype=np.float32), normalize=False, enable_sampling=False)
        sigma = mi.MarginalDiscrete2D0(np.ascontiguousarray(fields["sigma"], dtype=np.float32), normalize=False, enable_sampling=False)
        grid = mi.Point2f(x.reshape(-1).astype(np.float32), y.reshape(-1).astype(np.float32))
        for p in range(P):
            for t in range(T):
                ph, th = float(phi_i[p]), float(theta_i[t])
                param = mi.Point2f(np.full(n, ph, np.float32), np.full(n, th, np.float32))
                u_m, _ = vndf.sample(grid, param)
                u_m = np.array(u_m, dtype=np.float64).reshape(2, n)
                theta_m = u_m[0] ** 2 * (np.pi / 2)                 # the plugin's u2theta, u2phi (+ phi_i: isotropic)
                phi_m = (2.0 * u_m[1] - 1.0) * np.pi + ph
                m = np.stack([np.cos(phi_m) * np.sin(theta_m), np.sin(phi_m) * np.sin(theta_m), np.cos(theta_m)], axis=-1)
                sensor = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
                light = 2.0 * (m @ sensor)[:, None] * m - sensor
                if jacobian:
                    d = np.array(ndf.eval(mi.Point2f(u_m[0].astype(np.float32), u_m[1].astype(np.float32))), dtype=np.float64)
                    u_wi = mi.Point2f(np.full(1, np.sqrt(th * 2.0 / np.pi), np.float32), np.full(1, (ph + np.pi) / (2.0 * np.pi), np.float32))
                    s = float(np.array(sigma.eval(u_wi), dtype=np.float64).reshape(-1)[0])
                    factor = d / (4.0 * s) if s > 0 else np.zeros(n)
                else:
                    factor = np.ones(n)
                wis.append(light)
                wos.append(np.repeat(sensor[None], n, axis=0))
                factors.append(factor)
    return np.concatenate(wis), np.concatenate(wos), np.concatenate(factors), (P, T, C, H, W)


def fit_on_rgl_grid(model, params, source, out, *, description: str = "", variant: str | None = None,
                    verify=None) -> dict:
    """Write ``model`` at ``params`` as an RGL ``.bsdf`` file on ``source``'s grid.

    Every value node gets the model's f_r cos(theta_wi) over the plugin's factor at its
    direction pair (:func:`grid_directions`); a node with no value of its own (its sampled
    direction at or below the horizon, where the plugin never evaluates, or a zero factor)
    takes its nearest neighbour's in the slice. An incidence slice the source holds
    as a copy of the one before (RGL files repeat their last measured incidence at 90 deg) is
    written as the same copy of the fit's, so the file extends the fit beyond the measured
    incidences as the source extends the data. Every other field is the source's, except
    ``description`` (``description``, printable ASCII).

    The file is loaded by Mitsuba's ``measured`` and handed to ``verify(tmp_path)`` (where
    given; it raises to refuse) before it gets its name: a refusal leaves nothing.

    Returns a summary dict: ``nodes``, ``held`` (the nodes without a value of their own),
    ``copied_slices``, ``path``.

    Raises
    ------
    ValueError
        One line: the source is not an isotropic RGB RGL file, or the model is not finite
        at a node.
    """
    fields = read_tensor(source)
    wi, wo, factor, (P, T, C, H, W) = grid_directions(fields, variant)
    up = (wi[:, 2] > 0.0) & (factor > 0.0)
    f = np.zeros((wi.shape[0], C))
    if up.any():
        f[up] = np.asarray(model.eval(wi[up], wo[up], params), dtype=np.float64).reshape(-1, C)
    if not np.all(np.isfinite(f)):
        raise ValueError(f"the model is not finite at {int((~np.isfinite(f).all(axis=1)).sum())} of the grid's nodes")
    values = np.zeros_like(f)
    values[up] = f[up] * wi[up, 2:3] / factor[up, None]
    values = _hold_below_horizon(values.reshape(P, T, H, W, C), up.reshape(P, T, H, W))
    table = values.transpose(0, 1, 4, 2, 3).astype(np.float32)
    if not np.all(np.isfinite(table)):
        raise ValueError("a value on the grid overflows float32: the model is far above the source's NDF somewhere")
    source_table = fields["rgb"]
    copied = [t for t in range(1, T) if np.array_equal(source_table[:, t], source_table[:, t - 1])]
    for t in copied:
        table[:, t] = table[:, t - 1]
    text = "".join(ch if 32 <= ord(ch) < 127 else " " for ch in str(description)) or "gonio fit"
    fields["description"] = np.frombuffer(text.encode("ascii"), dtype=np.uint8).copy()
    fields["rgb"] = np.ascontiguousarray(table)

    def loads(tmp):
        from gonio.fitting.formats import RGLBRDF

        RGLBRDF(tmp, variant)
        if verify is not None:
            verify(tmp)

    path = write_tensor(out, fields, verify=loads)
    return {"path": path, "nodes": int(up.size), "held": int((~up).sum()), "copied_slices": copied}


def grid_error(model, params, path, wi=None, wo=None, variant: str | None = None) -> float:
    """How far the RGL file at ``path`` (Mitsuba's ``measured``) is from ``model`` at
    ``params``: Ngan 2005's cosine-weighted relative L2 of its f_r against the model's at
    (``wi``, ``wo``), by default the equal-solid-angle pairs below 80 deg
    (:func:`~gonio.core.geometry.equal_solid_angle_pairs`). For a fit written on a grid, the
    format's interpolation between the measured incidences and its copied last incidence are
    what it measures."""
    from gonio.core.geometry import equal_solid_angle_pairs
    from gonio.fitting.formats import RGLBRDF

    if wi is None:
        wi, wo = equal_solid_angle_pairs()
    cos_i = np.clip(np.asarray(wi)[:, 2:3], 0.0, 1.0)
    want = np.asarray(model.eval(wi, wo, params), dtype=np.float64)
    got = RGLBRDF(path, variant).eval(wi, wo)
    norm = float(np.sum((want * cos_i) ** 2))
    if not np.all(np.isfinite(got)) or not norm > 0.0:
        raise ValueError("the written file's values or the model's are not finite, or the model is zero on the grid")
    return float(np.sqrt(np.sum(((got - want) * cos_i) ** 2) / norm))


def _hold_below_horizon(values, up):
    """Each node below the horizon takes the value of the nearest node above it in the same
    slice (sample-grid distance): the plugin interpolates between nodes on both sides of the
    horizon, and a held value keeps that interpolation at the fit's values, where a 0 would
    pull the last degrees above the horizon towards black."""
    from scipy.ndimage import distance_transform_edt

    out = values.copy()
    for p in range(values.shape[0]):
        for t in range(values.shape[1]):
            above = up[p, t]
            if above.all() or not above.any():
                continue
            _, (j, k) = distance_transform_edt(~above, return_indices=True)
            out[p, t] = values[p, t][j, k]
    return out
