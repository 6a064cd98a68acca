"""Plots of measured and fitted BRDFs for notebooks and reports (matplotlib).

Each function draws on the Axes it is given (or on a new Figure) and returns the Figure, so a
notebook shows it and a report saves it (``fig.savefig(buf, format="png")``). Text that comes
from data (channel labels) passes through :func:`safe_label`: matplotlib never reads it as
mathtext.

* :func:`plot_in_plane`: f_r in the plane of incidence against the signed outgoing angle
  (negative on the light's side), one panel per incidence angle, with the fitted model's curve;
* :func:`plot_coverage`: the detector directions on a polar plot, coloured by theta_i;
* :func:`plot_residuals`: normalised residuals (measured - fit) / sigma, histogram and per point.

Angles follow gonio.core.geometry (theta from the normal, phi = atan2(y, x)); a point is in
the plane of incidence when |phi_i - phi_o| is within 5 degrees of 180 or 0 (or either
direction is within 1 degree of the normal).
"""

from __future__ import annotations

import numpy as np

from gonio.core.geometry import angles_deg

__all__ = ["plot_coverage", "plot_in_plane", "incidence_groups", "plot_residuals", "safe_label", "in_plane_mask", "log_ticks", "transmits",
           "shade_transmitted"]

COLOURS = ("tab:red", "tab:green", "tab:blue")


def safe_label(text, limit: int = 40) -> str:
    """Text made safe for a matplotlib label: printable, no mathtext, at most ``limit`` characters."""
    s = "".join(ch if ch.isprintable() else "?" for ch in str(text))[:limit]
    return s.replace("\\", "/").replace("$", r"\$")


def log_ticks(axis) -> None:
    """Log-axis labels at 1, 2 and 5 times a power of ten only: over less than a decade
    matplotlib labels every minor tick (2x10^-1, 3x10^-1, ...), and they run into each other."""
    from matplotlib.ticker import LogFormatterSciNotation, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0), numticks=12))
    axis.set_major_formatter(LogFormatterSciNotation(labelOnlyBase=False))
    axis.set_minor_formatter(NullFormatter())


def _figure(ax, n=1, **kw):
    import matplotlib.pyplot as plt

    if ax is not None:
        return ax.figure, np.atleast_1d(ax)
    fig, axes = plt.subplots(1, n, squeeze=False, layout="constrained", **kw)
    return fig, axes[0]


def in_plane_mask(meas):
    """(phi_d in degrees in [0, 180], mask of the points in the plane of incidence)."""
    theta_i, phi_i = angles_deg(meas.wi)
    theta_o, phi_o = angles_deg(meas.wo)
    phi_d = np.degrees(np.abs(np.angle(np.exp(1j * np.radians(phi_i - phi_o)))))
    return phi_d, (phi_d > 175) | (phi_d < 5) | (theta_i < 1) | (theta_o < 1) | (theta_o > 179)


def transmits(meas, model=None) -> bool:
    """Whether a figure shows the transmitted side too: a measured point below the surface
    (theta_o > 90) or a model that transmits (:mod:`gonio.core.sides`)."""
    from gonio.core.sides import Side

    if np.any(np.asarray(meas.wo)[:, 2] < 0.0):
        return True
    return model is not None and Side.TRANSMIT in tuple(model.structure.sides)


def shade_transmitted(ax) -> None:
    """A light band over theta_o beyond 90 deg (the transmitted side) of an in-plane axis."""
    for lo, hi in ((-180.0, -90.0), (90.0, 180.0)):
        ax.axvspan(lo, hi, color="0.5", alpha=0.08, lw=0)


def incidence_groups(theta_i, gap: float = 0.5) -> list:
    """The incidence angles ``theta_i`` (degrees) sorted and split where consecutive values
    differ by more than ``gap``: one array per measured incidence, however its points were moved
    by a fraction of a degree (the shared-angle estimate moves them together)."""
    t = np.sort(np.asarray(theta_i, float))
    if not t.size:
        return []
    return np.split(t, np.flatnonzero(np.diff(t) > gap) + 1)


def plot_in_plane(meas, model=None, params=None, *, incidences=None, max_panels: int = 4, log: bool = True):
    """Measured f_r (with 1-sigma bars) in the plane of incidence, and the model's curve.

    Parameters
    ----------
    meas : Measurements
        The data.
    model, params : optional
        A gonio model and its parameter values (a fit's ``result.model``, ``result.params``).
    incidences : sequence of float, optional
        The incidence angles (degrees) to show; by default up to ``max_panels`` of the measured
        ones: the in-plane points' theta_i split where consecutive values differ by more than
        0.5 deg, each group at its median (so a group the shared-angle estimate moved by a
        fraction of a degree, 29.6 or 30.5, stays one panel at its own angle).
    log : bool
        Logarithmic f_r axis.

    Returns
    -------
    matplotlib.figure.Figure
        Empty of panels (one note in its title) when no point lies in the plane of incidence.
    """
    theta_i, _ = angles_deg(meas.wi)
    theta_o, _ = angles_deg(meas.wo)
    phi_d, plane = in_plane_mask(meas)
    groups = incidence_groups(theta_i[plane])
    if incidences is None:
        chosen = groups if len(groups) <= max_panels else [groups[int(k)] for k in np.linspace(0, len(groups) - 1, max_panels)]
        incidences = [float(np.median(g)) for g in chosen]
        members = [(g[0], g[-1]) for g in chosen]
    else:
        members = [(ti - 0.6, ti + 0.6) for ti in incidences]
    if not len(incidences):
        fig, _ = _figure(None, 1, figsize=(4, 1))
        fig.suptitle("no measured point in the plane of incidence", fontsize=9)
        return fig
    fig, axes = _figure(None, len(incidences), figsize=(2.9 * len(incidences) + 0.6, 3.0), sharey=True)
    both = transmits(meas, model)       # the whole plane: |theta_o| > 90 is the transmitted side
    t = np.radians(np.linspace(-179, 179, 481) if both else np.linspace(-89, 89, 241))
    for ax, ti, (lo, hi) in zip(axes, incidences, members):
        sel = plane & (theta_i >= lo) & (theta_i <= hi)
        signed = np.where(phi_d[sel] < 90, -theta_o[sel], theta_o[sel])
        curve = None
        if model is not None:
            wi = np.tile([np.sin(np.radians(ti)), 0.0, np.cos(np.radians(ti))], (t.size, 1))
            wo = np.stack([-np.sin(t), np.zeros_like(t), np.cos(t)], axis=-1)        # +t on the mirror side
            curve = model.eval(wi, wo, params)
        for c in range(meas.n_channels):
            name = safe_label(meas.channels[c], 12) if c < len(meas.channels) else str(c)
            ax.errorbar(signed, meas.brdf[sel, c], yerr=meas.brdf_std[sel, c], fmt="o", ms=3,
                        color=COLOURS[c % 3], label=name if ax is axes[0] else None)
            if curve is not None:
                ax.plot(np.degrees(t), curve[:, c], "-", lw=1, color=COLOURS[c % 3])
        if log:
            ax.set_yscale("log")
            log_ticks(ax.yaxis)
        if both:
            shade_transmitted(ax)
            ax.set_xlim(-180, 180)
            ax.set_xticks([-150, -90, -30, 30, 90, 150])
        else:
            ax.set_xlim(-90, 90)
            ax.set_xticks([-60, -30, 0, 30, 60])
        ax.set_title(f"theta_i = {round(ti, 1):g} deg", fontsize=9)
        ax.set_xlabel("theta_o (deg)", fontsize=8)      # < 0 on the light's side
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("f_r (1/sr)", fontsize=8)
    fig.legend(fontsize=7, loc="outside lower center", frameon=False, ncol=3)
    return fig


def plot_coverage(meas, ax=None):
    """The detector directions (r = theta_o in degrees, angle = phi_o), coloured by theta_i."""
    import matplotlib.pyplot as plt

    theta_i, _ = angles_deg(meas.wi)
    theta_o, phi_o = angles_deg(meas.wo)
    if ax is None:
        fig, ax = plt.subplots(subplot_kw={"projection": "polar"}, figsize=(4.6, 4.4), layout="constrained")
    fig = ax.figure
    sc = ax.scatter(np.radians(phi_o), theta_o, c=theta_i, cmap="viridis", s=14)
    if transmits(meas):                 # out to 180: beyond the 90 deg circle, the transmitted side
        ax.set_ylim(0, 180)
        ax.set_rticks([45, 90, 135, 180])
        ax.plot(np.linspace(0, 2 * np.pi, 181), np.full(181, 90.0), color="0.3", lw=1)
    else:
        ax.set_ylim(0, 90)
        ax.set_rticks([30, 60, 90])
    ax.set_rlabel_position(112.5)
    ax.tick_params(labelsize=8)
    ax.set_title("detector directions (r = theta_o, colour = theta_i)", fontsize=9)
    fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.1, label="theta_i (deg)")
    return fig


def plot_residuals(meas, model, params):
    """(measured - fit) / sigma: a histogram of the used values and the rms per point over (theta_i, theta_o)."""
    theta_i, _ = angles_deg(meas.wi)
    theta_o, _ = angles_deg(meas.wo)
    resid = (meas.brdf - model.eval(meas.wi, meas.wo, params)) / meas.brdf_std
    fig, axes = _figure(None, 2, figsize=(8, 3.2))
    axes[0].hist(resid[meas.use].ravel(), bins=40, color="grey")
    axes[0].set_xlabel("(measured - fit) / sigma")
    axes[0].set_title("fit residuals", fontsize=9)
    rms = np.sqrt(np.mean(np.where(meas.use, resid, 0.0) ** 2, axis=1))
    sc = axes[1].scatter(theta_i, theta_o, c=rms, cmap="magma", s=16)
    axes[1].set_xlabel("theta_i (deg)")
    axes[1].set_ylabel("theta_o (deg)")
    axes[1].set_title("rms residual / sigma per point", fontsize=9)
    fig.colorbar(sc, ax=axes[1])
    return fig
