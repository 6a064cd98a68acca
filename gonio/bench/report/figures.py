"""The report's figures (matplotlib, PNG bytes), drawn from values the report has checked.

Each figure function returns ``{file name: PNG bytes}``; :func:`draw` runs them and turns a
figure that cannot be drawn (a degenerate posterior, values matplotlib refuses) into a note
for the report instead of a traceback. Text from input files reaches a figure only through
:func:`label`, which stops matplotlib reading it as mathtext.
"""

from __future__ import annotations

import io

import numpy as np

from gonio.fitting.plots import (in_plane_mask, log_ticks, plot_coverage, plot_in_plane, plot_residuals,
                                 safe_label)
from gonio.core.geometry import angles as _angles

__all__ = ["draw", "label", "legible", "css_width", "printed_scale", "DPI", "MIN_PRINT_PT", "PRINT_WIDTH_IN"]

COLOURS = ["tab:red", "tab:green", "tab:blue"]
#: the figures' resolution (PNG pixels per figure inch)
DPI = 110
#: the printed page's text width (inches): A4, 210 mm, less the print stylesheet's 14 mm margins
PRINT_WIDTH_IN = (210.0 - 2 * 14.0) / 25.4
#: the smallest font (pt) a figure shows when the report is printed on A4
MIN_PRINT_PT = 8.0
#: the widest a figure is drawn (inches), so that it prints at its own size (scale 1)
MAX_WIDTH_IN = 6.9
_PAD_IN = 0.1             # savefig's pad_inches around the tight bounding box


_log_ticks = log_ticks
label = safe_label


def printed_scale(width_in: float) -> float:
    """How much a figure ``width_in`` inches wide is shrunk when printed: the report prints a
    figure at its own size (its ``width`` attribute, :func:`css_width`), scaled down only to
    the page's text width."""
    return min(1.0, PRINT_WIDTH_IN / max(width_in, 1e-6))


def _texts(fig):
    from matplotlib.text import Text

    return [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]


def legible(fig) -> float:
    """Enlarge every text of ``fig`` (titles, labels, tick labels, legends, colour bars) to at
    least :data:`MIN_PRINT_PT` as printed: its size times the figure's printed scale (its saved,
    tight width). Returns the smallest printed size (pt) after the change."""
    renderer = fig.canvas.get_renderer()
    for attempt in range(4):                        # larger labels can widen the tight box
        fig.canvas.draw()
        width = fig.get_tightbbox(renderer).width + 2 * _PAD_IN
        need = MIN_PRINT_PT / printed_scale(width) + 1e-3
        small = False
        for ax in fig.axes:
            for which, axis in (("x", ax.xaxis), ("y", ax.yaxis)):
                labels = axis.get_ticklabels(which="both")
                if labels and min(t.get_fontsize() for t in labels) < need:
                    ax.tick_params(axis=which, which="both", labelsize=need)
                    small = True
        for t in _texts(fig):
            if t.get_fontsize() < need:
                t.set_fontsize(need)
                small = True
        if not small or attempt == 3:
            break
    return min((t.get_fontsize() for t in _texts(fig)), default=MIN_PRINT_PT) * printed_scale(width)


def css_width(png: bytes) -> int | None:
    """The width (CSS px, 96 an inch) at which a PNG is its physical size: its pixels over its
    resolution (the pHYs chunk matplotlib writes; :data:`DPI` when absent); None when not a PNG."""
    import struct

    if len(png) < 33 or png[12:16] != b"IHDR":
        return None
    width = struct.unpack(">I", png[16:20])[0]
    dpi, at = float(DPI), 8
    while at + 8 <= min(len(png), 1 << 16):       # pHYs comes before the image data
        size, kind = struct.unpack(">I", png[at:at + 4])[0], png[at + 4:at + 8]
        if kind == b"pHYs" and size == 9 and png[at + 16] == 1:       # unit: metre
            ppm = struct.unpack(">I", png[at + 8:at + 12])[0]
            dpi = ppm * 0.0254 if ppm > 0 else dpi
            break
        if kind in (b"IDAT", b"IEND"):
            break
        at += 12 + size
    return max(1, round(width * 96.0 / dpi))


def _save(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight", pad_inches=_PAD_IN)
    finally:
        plt.close(fig)
    return buf.getvalue()


def _png(fig) -> bytes:
    """The figure as PNG bytes, its texts made legible in print first (:func:`legible`)."""
    legible(fig)
    return _save(fig)


def draw(images: dict, notes: list, name: str, fn, *args) -> None:
    """Add ``fn(*args)``'s figures to ``images``; on failure add a note saying which and why."""
    import matplotlib.pyplot as plt

    try:
        images.update(fn(*args))
    except (ValueError, TypeError, IndexError, OverflowError, FloatingPointError, RuntimeError) as exc:
        plt.close("all")
        notes.append(f"figure {name} could not be drawn: {' '.join(str(exc).split())[:200]}")


def angles(meas):
    theta_i, phi_i = _angles(meas.wi)
    theta_o, phi_o = _angles(meas.wo)
    return np.degrees(theta_i), np.degrees(theta_o), phi_i, phi_o


def coverage(meas) -> dict:
    """The detector directions (`gonio.fitting.plots.plot_coverage`)."""
    return {"coverage.png": _png(plot_coverage(meas))}


def _in_plane(meas):
    return in_plane_mask(meas)


def inplane(meas, model=None, params=None) -> dict:
    """Measured (and fitted, where a fit is given), in the plane of incidence, for up to four
    incidence angles (`gonio.fitting.plots.plot_in_plane`): ``inplane.png`` with a fit,
    ``measured.png`` without; nothing when no point lies in the plane."""
    if not np.any(in_plane_mask(meas)[1]):
        return {}
    fig = plot_in_plane(meas, model, params)
    _two_columns(fig)
    return {("inplane.png" if model is not None else "measured.png"): _png(fig)}


def _two_columns(fig, panel_in: float = 3.15, row_in: float = 2.7) -> None:
    """More than two panels in a row (the in-plane plot's incidences) laid out two to a row, so
    the figure prints at its own size on A4 and its labels keep their size."""
    from matplotlib.gridspec import GridSpec

    axes = [ax for ax in fig.axes if ax.get_subplotspec() is not None]
    if len(axes) <= 2:
        return
    rows = (len(axes) + 1) // 2
    grid = GridSpec(rows, 2, figure=fig)
    ylabel = axes[0].get_ylabel()
    for k, ax in enumerate(axes):
        ax.set_subplotspec(grid[k // 2, k % 2])
        ax.yaxis.set_tick_params(labelleft=True)
        if k % 2 == 0 and ylabel:
            ax.set_ylabel(ylabel, fontsize=axes[0].yaxis.label.get_fontsize())
    fig.set_size_inches(2 * panel_in + 0.5, row_in * rows + 0.5)


def polar(meas, model, params) -> dict:
    """At the incidence with the most out-of-plane points: the fit over the whole hemisphere
    (background), the measurements on the same colour scale (dots), and their ratio; one
    figure per side the data holds (``polar.png`` reflected, ``polar_transmitted.png``)."""
    below = np.asarray(meas.wo)[:, 2] < 0.0
    out = {}
    for name, side in (("polar.png", ~below), ("polar_transmitted.png", below)):
        if side.any():
            out.update(_polar_side(meas, model, params, side, name))
    return out


def _polar_side(meas, model, params, side, name) -> dict:
    """:func:`polar` for the points ``side`` (N,) of one hemisphere: the transmitted one is drawn
    about -z, radius 180 - theta_o (the angle from the straight-through axis of a normal beam)."""
    import matplotlib
    import matplotlib.pyplot as plt

    theta_i, theta_o, phi_i, phi_o = angles(meas)
    through = name != "polar.png"
    _, in_plane = _in_plane(meas)
    out_of_plane = ~in_plane & side
    if not out_of_plane.any():
        return {}
    fitted = model.eval(meas.wi, meas.wo, params)
    groups, counts = np.unique(np.round(theta_i[out_of_plane]), return_counts=True)
    ti = float(groups[np.argmax(counts)])
    sel = (np.abs(theta_i - ti) < 0.6) & side
    phi_in = float(np.median(phi_i[sel]))
    t, p = np.meshgrid(np.radians(np.linspace(0, 85, 60)), np.radians(np.linspace(-180, 180, 121)))
    wo_g = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), (-1.0 if through else 1.0) * np.cos(t)],
                    axis=-1).reshape(-1, 3)
    radius = 180.0 - theta_o if through else theta_o
    wi_g = np.tile([np.sin(np.radians(ti)) * np.cos(phi_in), np.sin(np.radians(ti)) * np.sin(phi_in),
                    np.cos(np.radians(ti))], (wo_g.shape[0], 1))
    c = 1 if meas.n_channels > 1 else 0
    grid = model.eval(wi_g, wo_g, params)[:, c].reshape(t.shape)
    norm = matplotlib.colors.LogNorm(vmin=max(float(grid.min()), 1e-4), vmax=float(grid.max()))
    # colour bars below their plots: beside them their labels met the next plot's 180 deg label
    fig, axes = plt.subplots(1, 2, subplot_kw={"projection": "polar"}, figsize=(MAX_WIDTH_IN - 0.2, 4.3),
                             layout="constrained")
    where = "transmitted, radius 180 - theta_o" if through else "reflected"
    for ax, title in zip(axes, (f"fit (background), measured (dots)\n{where}, theta_i = {ti:.0f} deg",
                                "measured / fit")):
        ax.set_ylim(0, 85)
        ax.set_rticks([30, 60])
        ax.set_rlabel_position(112.5)
        ax.tick_params(labelsize=8)
        ax.set_title(title, fontsize=9)
    mesh = axes[0].pcolormesh(p, np.degrees(t), grid, norm=norm, cmap="viridis", shading="auto")
    axes[0].scatter(phi_o[sel], radius[sel], c=meas.brdf[sel, c], norm=norm, cmap="viridis", edgecolors="white", s=28)
    bar = fig.colorbar(mesh, ax=axes[0], shrink=0.6, orientation="horizontal", pad=0.08)
    bar.set_label(f"f_r {label(meas.channels[c])} (1/sr)", fontsize=8)
    bar.ax.tick_params(labelsize=8)
    bar.ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(numticks=4))
    bar.ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ratio = meas.brdf[sel, c] / np.maximum(fitted[sel, c], 1e-12)
    # the colour range from the ratios' median absolute deviation: a point whose fit is ~0 (noise
    # past a transmitted lobe's edge) would stretch a standard deviation to 1e5 and grey out the rest
    spread = 3 * 1.4826 * float(np.median(np.abs(ratio - np.median(ratio)))) + 1e-6
    sc = axes[1].scatter(phi_o[sel], radius[sel], c=ratio, cmap="coolwarm", s=28, vmin=1 - spread, vmax=1 + spread)
    bar = fig.colorbar(sc, ax=axes[1], shrink=0.6, orientation="horizontal", pad=0.08, extend="both")
    bar.set_label("measured / fit", fontsize=8)
    bar.ax.tick_params(labelsize=8)
    bar.ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(3))
    bar.ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.4g"))
    return {name: _png(fig)}


def residuals(meas, model, params) -> dict:
    """Normalised residuals (`gonio.fitting.plots.plot_residuals`)."""
    fig = plot_residuals(meas, model, params)
    w, h = fig.get_size_inches()
    if w > MAX_WIDTH_IN:                      # printed at its own size on A4
        fig.set_size_inches(MAX_WIDTH_IN, h * MAX_WIDTH_IN / w)
    return {"residuals.png": _png(fig)}


def albedo(model, params) -> dict:
    """Directional albedo of the fit; for a model that transmits, its reflectance R, its
    transmittance T and R + T against the incidence (:func:`reflectance_transmittance`)."""
    import matplotlib.pyplot as plt

    from gonio.core.sides import Side

    t = np.radians(np.linspace(0, 85, 35))
    fig, ax = plt.subplots(figsize=(4.2, 3.0), layout="constrained")
    if Side.TRANSMIT in tuple(model.structure.sides):
        R, T = reflectance_transmittance(model, params, t)
        for v, style, name in ((R, "--", "R"), (T, ":", "T"), (R + T, "-", "R + T")):
            for c in range(R.shape[1]):
                ax.plot(np.degrees(t), v[:, c], style, color=COLOURS[c % 3])
            ax.plot([], [], style, color="0.2", label=name)
        ax.legend(fontsize=8, frameon=False)
        ax.set_xlabel("theta_i (deg)")
        ax.set_ylabel("reflectance, transmittance")
        top = float(np.max(R + T))
    else:
        wo_a = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], axis=-1)
        alb = model.albedo(wo_a, params)
        for c in range(alb.shape[1]):
            ax.plot(np.degrees(t), alb[:, c], color=COLOURS[c % 3])
        ax.set_xlabel("theta_o (deg)")
        ax.set_ylabel("directional albedo")
        top = float(alb.max())
    ax.set_ylim(0, max(1.05, top * 1.05))
    return {"albedo.png": _png(fig)}


def reflectance_transmittance(model, params, theta_i, n=1 << 16, seed=0):
    """R and T (len(theta_i), C) of light arriving from each theta_i (radians, phi_i = 0): the
    mean weight f |cos theta_o| / pdf of ``n`` directions that the fit's Mitsuba BSDF samples
    in importance mode (Veach 1997, 3.7.6: the adjoint BSDF, light leaving the lit face or the
    far one; a smooth interface's delta lobes included), split by the side each leaves on.
    Stratified sample points from a seeded Generator: a standard error of about 1e-3."""
    import drjit as dr
    import mitsuba as mi

    from gonio.models.mitsuba import select_variant

    variant = select_variant()
    rng = np.random.default_rng(seed)
    k = int(np.sqrt(n))
    g = (np.arange(k) + 0.5) / k
    u1, u2 = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    jitter = rng.random((3, u1.size)) / k
    s1, s2 = (np.clip(u1 + jitter[0] - 0.5 / k, 0, 1 - 1e-7), np.clip(u2 + jitter[1] - 0.5 / k, 0, 1 - 1e-7))
    lobe = rng.permutation(u1.size) / u1.size + jitter[2] / u1.size            # the lobe choice, stratified too
    R, T = [], []
    with mi.scoped_set_variant(variant):
        bsdf = mi.load_dict(model.to_mitsuba(params))
        ctx = mi.BSDFContext(mi.TransportMode.Importance)
        for ti in np.atleast_1d(theta_i):
            si = dr.zeros(mi.SurfaceInteraction3f, u1.size)
            si.wi = mi.Vector3f(float(np.sin(ti)), 0.0, float(np.cos(ti)))
            si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
            si.n = mi.Normal3f(0.0, 0.0, 1.0)
            bs, w = bsdf.sample(ctx, si, mi.Float(lobe.astype(np.float32)),
                                mi.Point2f(s1.astype(np.float32), s2.astype(np.float32)))
            w = np.broadcast_to(np.array(w, dtype=np.float64).reshape(3, -1).T, (u1.size, 3))   # a constant weight has width 1
            w = np.where(np.isfinite(w), w, 0.0)
            up = np.broadcast_to(np.array(bs.wo, dtype=np.float64).reshape(3, -1)[2] > 0.0, (u1.size,))
            R.append(np.where(up[:, None], w, 0.0).mean(axis=0))
            T.append(np.where(~up[:, None], w, 0.0).mean(axis=0))
    return np.array(R), np.array(T)


def corner_plot(samples: np.ndarray, names, converged: bool) -> dict:
    import corner

    from matplotlib.ticker import ScalarFormatter

    k = samples.shape[1]
    # each parameter shown as its offset from the posterior median, so tick labels stay short
    # (the absolute values made matplotlib print offset texts such as "1e-5+1.2e-1" over them)
    from matplotlib.ticker import MaxNLocator

    centre = np.median(samples, axis=0)
    spread = np.std(samples, axis=0)
    scale = 10.0 ** np.floor(np.log10(np.where(spread > 0, spread, 1.0)))
    names = [label(n) for n in names] if names else [f"p{i}" for i in range(k)]
    labels = [f"{n}\n- {c:.6g}" + (f", in {s:.0e}" if s != 1 else "") for n, c, s in zip(names, centre, scale)]
    fig = corner.corner((samples - centre) / scale, labels=labels, quantiles=[0.05, 0.5, 0.95],
                        label_kwargs={"fontsize": 8}, max_n_ticks=3, labelpad=0.08)
    size = min(max(3.0, 1.9 * k), MAX_WIDTH_IN)        # printed at its own size on A4
    fig.set_size_inches(size, size)
    for idx, ax in enumerate(fig.axes):
        i, j = divmod(idx, k)           # row, column of corner's k x k grid
        if j > i:                       # its hidden upper triangle
            continue
        ax.tick_params(labelsize=8, labelrotation=0)
        # no tick at an axes' edge (there the labels of neighbouring axes met); labels, without
        # an offset text, only where corner shows them: the bottom row and the first column
        axes = [(ax.xaxis, i == k - 1)] + ([(ax.yaxis, j == 0)] if j < i else [])
        for axis, labelled in axes:
            axis.set_major_locator(MaxNLocator(3, prune="both"))
            if labelled:
                axis.set_major_formatter(ScalarFormatter(useOffset=False))
    fig.suptitle("posterior (emcee)" + ("" if converged else ": chain too short, see advice"), fontsize=9)
    return {"corner.png": _png(fig)}


def mitsuba_vs_measured(meas, rendered: np.ndarray) -> dict:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.2, 4.0), layout="constrained")
    for c in range(min(3, rendered.shape[1], meas.n_channels)):
        ax.loglog(meas.brdf[:, c], rendered[:, c], "o", ms=3, color=COLOURS[c])
    positive = meas.brdf[meas.brdf > 0]
    lim = [max(1e-4, float(np.min(positive)) * 0.8 if positive.size else 1e-4), max(float(np.max(meas.brdf)) * 1.2, 1e-3)]
    ax.plot(lim, lim, "k--", lw=0.8)
    _log_ticks(ax.xaxis)
    _log_ticks(ax.yaxis)
    ax.set_xlabel("measured f_r (1/sr)")
    ax.set_ylabel("Mitsuba render of the fit (1/sr)")
    return {"mitsuba_vs_measured.png": _png(fig)}


def preview(tiles, rows) -> dict:
    """The sphere previews of `gonio render --preview` (PNG bytes per lighting: the fit's, and
    with --measured the measured BSDF's and the CIEDE2000 map's) in one figure that prints at its
    own size: one row per lighting, titles and the colour bar's labels at 8 pt or more."""
    import matplotlib
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt

    stats = {r["lighting"]: r for r in rows}
    ncols = 3 if "measured_png" in tiles[0][1] else 1
    tile_in = 2.0
    fig, axes = plt.subplots(len(tiles), ncols, squeeze=False, layout="constrained",
                             figsize=(tile_in * ncols + (0.6 if ncols == 3 else 0.3), (tile_in + 0.45) * len(tiles)))
    for r, (lighting, tile) in enumerate(tiles):
        panels = [("model_png", f"fitted model ({lighting})")]
        if ncols == 3:
            s = stats.get(lighting, {})
            panels += [("measured_png", f"measured ({lighting})"),
                       ("delta_e_png", f"CIEDE2000: mean {s.get('mean', '?')}, p95 {s.get('p95', '?')}")]
        for c, (key, title) in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(mpimg.imread(io.BytesIO(tile[key]), format="png"))
            ax.set_title(title, fontsize=8.5)
            ax.set_xticks([])
            ax.set_yticks([])
        if ncols == 3:
            # the map's own scale (gonio/fitting/render/preview.py: magma, 0 to max(5, p95))
            try:
                vmax = max(5.0, float(stats.get(lighting, {}).get("p95", 5.0)))
            except (TypeError, ValueError):
                vmax = 5.0
            bar = fig.colorbar(matplotlib.cm.ScalarMappable(matplotlib.colors.Normalize(0.0, vmax), "magma"),
                               ax=axes[r, 2], fraction=0.046, pad=0.04)
            bar.ax.tick_params(labelsize=8)
    return {"preview_side_by_side.png": _png(fig)}


def text_overlaps(fig) -> list[tuple[str, str]]:
    """Pairs of text artists of ``fig`` that a draw actually draws (tick labels outside the view
    are not) whose tight bounding boxes, in display pixels, intersect: labels printed over
    each other. Used by the suite on every figure of the report."""
    from matplotlib.text import Text

    drawn = []
    original = Text.draw

    def record(self, renderer):
        original(self, renderer)
        if self.get_visible() and self.get_text().strip():
            drawn.append((self.get_text(), self.get_window_extent(renderer)))

    Text.draw = record
    try:
        fig.canvas.draw()
    finally:
        Text.draw = original
    out = []
    for a in range(len(drawn)):
        for b in range(a + 1, len(drawn)):
            ba, bb = drawn[a][1], drawn[b][1]
            # strict intersection (touching edges is not overlapping)
            if ba.x0 < bb.x1 and bb.x0 < ba.x1 and ba.y0 < bb.y1 and bb.y0 < ba.y1:
                out.append((drawn[a][0], drawn[b][0]))
    return out
