"""Spectral plans: every geometry of a plan at every wavelength of a monochromator's grid.

A plan's ``[spectral]`` table (``from_nm``, ``to_nm``, ``step_nm``) expands its geometries into
one point per (geometry, wavelength), each with its ``wavelength_nm`` (`grid`, `expand`); the
``spectral`` preset is the ``quick`` geometry times 400-700 nm, ``spectral:STEP`` another step.
`spectral_order` orders such a plan with wavelength as the fastest axis (every wavelength at a
geometry, sweeping up then down on alternate geometries) or the slowest (the geometry tour at
each wavelength, forwards then backwards), whichever the estimate says takes less time: the
stages' move time (`gonio.bench.plan.ordering.path_time`) plus the monochromator's
(`MonochromatorTimes`: grating turret, filter wheel, wavelength drive). Fastest pays one grating
change per geometry whose sweep crosses a grating boundary; slowest pays one stage tour per
wavelength. `check_wavelengths` refuses a wavelength the monochromator's ranges do not cover.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gonio.bench.drivers.monochromator import DEFAULTS, choose, ranges
from gonio.bench.plan.ordering import OrderResult, order_moves, path_time
from gonio.core.errors import GonioError, PlanError

__all__ = ["MAX_WAVELENGTHS", "grid", "with_step", "expand", "checked_wavelengths", "check_wavelengths",
           "MonochromatorTimes", "spectral_order", "SpectralOrder", "geometry_groups"]

#: most wavelengths in one grid (1 nm steps over 200 nm)
MAX_WAVELENGTHS = 201
#: the range `gonio.core.channels.Channels` takes a spectral channel in, nm
LIMITS_NM = (200.0, 2500.0)


def _number(value, what: str, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PlanError(f"plan {name!r}: [spectral] {what} = {str(value)[:40]!r} is not a finite number of nm; "
                        "fix the plan file")
    return float(value)


def grid(table, name: str = "plan") -> np.ndarray:
    """The wavelengths (nm) of a ``[spectral]`` table: ``from_nm`` to ``to_nm`` every ``step_nm``
    (``to_nm`` included when a step lands on it); `PlanError` (one line) otherwise."""
    if not isinstance(table, Mapping) or set(table) != {"from_nm", "to_nm", "step_nm"}:
        raise PlanError(f"plan {name!r}: [spectral] takes from_nm, to_nm and step_nm (e.g. 400, 700, 20); "
                        "fix the plan file")
    lo, hi, step = (_number(table[k], k, name) for k in ("from_nm", "to_nm", "step_nm"))
    if not step > 0:
        raise PlanError(f"plan {name!r}: [spectral] step_nm = {step:g} must be positive; give e.g. 20")
    if not (LIMITS_NM[0] <= lo <= hi <= LIMITS_NM[1]):
        raise PlanError(f"plan {name!r}: [spectral] {lo:g}-{hi:g} nm must be increasing and within "
                        f"{LIMITS_NM[0]:g}-{LIMITS_NM[1]:g} nm; fix the plan file")
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    if n > MAX_WAVELENGTHS:
        raise PlanError(f"plan {name!r}: [spectral] {lo:g}-{hi:g} nm every {step:g} nm is {n} wavelengths, more "
                        f"than {MAX_WAVELENGTHS}; give a larger step_nm")
    return np.round(lo + step * np.arange(n), 6)


def with_step(doc: Mapping, text: str) -> dict:
    """The ``spectral`` preset's document with ``step_nm`` = ``text`` (``spectral:STEP``)."""
    try:
        step = float(text)
    except ValueError:
        raise PlanError(f"plan spectral:{text[:20]}: the step is not a number of nm; give e.g. spectral:20") from None
    out = dict(doc)
    out["spectral"] = {**doc["spectral"], "step_nm": step}
    return out


def expand(angles, wavelengths) -> tuple[np.ndarray, np.ndarray]:
    """Every geometry (rows of ``angles``) at every wavelength: (angles, wavelength_nm), geometry-major."""
    a, w = np.asarray(angles, float).reshape(-1, 4), np.asarray(wavelengths, float)
    return np.repeat(a, len(w), axis=0), np.tile(w, len(a))


def checked_wavelengths(wavelength_nm, name: str, n: int) -> np.ndarray:
    """A plan's per-point wavelengths: ``n`` finite numbers in `LIMITS_NM`; `PlanError` otherwise."""
    try:
        w = np.asarray(wavelength_nm, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise PlanError(f"plan {name!r}: wavelength_nm must be numbers (nm); fix the plan file") from None
    if w.size != n:
        raise PlanError(f"plan {name!r}: {w.size} wavelengths for {n} points; give one per point")
    bad = ~(np.isfinite(w) & (w >= LIMITS_NM[0]) & (w <= LIMITS_NM[1]))
    if bad.any():
        k = int(np.argmax(bad))
        raise PlanError(f"plan {name!r}: point {k} has wavelength {w[k]:g} nm, outside "
                        f"{LIMITS_NM[0]:g}-{LIMITS_NM[1]:g} nm; fix the plan file")
    return w


def check_wavelengths(wavelength_nm, settings: Mapping) -> None:
    """Refuse (`GonioError`, one line) a spectral plan on a bench without ``[monochromator]``, or
    a wavelength outside its ``gratings`` and ``filters`` ranges; before anything is written."""
    if not isinstance(settings.get("monochromator"), Mapping):
        raise GonioError("a spectral plan needs a monochromator: add a [monochromator] table to the settings "
                         "(gratings and filters) and give its port")
    t = MonochromatorTimes(settings)
    for w in np.unique(np.asarray(wavelength_nm, float)):
        if choose(t.gratings, w) is None or (t.filters and choose(t.filters, w) is None):
            lo, hi = t.range_nm
            raise GonioError(f"the plan's wavelength {w:g} nm is outside the monochromator's ranges ({lo:g}-{hi:g} nm "
                             "for [monochromator] gratings and filters); change the plan's [spectral] range")


class MonochromatorTimes:
    """How long the monochromator takes through a sequence of wavelengths: a grating change
    ``grating_s`` (and the drive back), ``filter_step_s`` per filter-wheel position (6 positions,
    the shortest way round), ``settle_s`` plus the slew at ``slew_nm_per_s`` x 1200 / lines
    (gratings of 1200, 600, 300 lines/mm). Figures: the simulated Cornerstone's timing model
    (gonio/sim/devices/monochromator.py), of the order of the MCS260 manual's."""

    LINES = {1: 1200, 2: 600, 3: 300}

    def __init__(self, settings: Mapping, grating_s: float = 6.0, filter_step_s: float = 0.8,
                 slew_nm_per_s: float = 175.0, settle_s: float = 0.05):
        m = settings.get("monochromator") or {}
        self.gratings = ranges(m.get("gratings", DEFAULTS["gratings"]), "gratings")
        self.filters = ranges(m.get("filters", DEFAULTS["filters"]), "filters", empty=True)
        self.grating_s, self.filter_step_s = grating_s, filter_step_s
        self.slew, self.settle_s = slew_nm_per_s, settle_s

    @property
    def range_nm(self) -> tuple[float, float]:
        rows = [self.gratings] + ([self.filters] if self.filters else [])
        return max(min(r[1] for r in t) for t in rows), min(max(r[2] for r in t) for t in rows)

    def run(self, wavelengths) -> tuple[float, int]:
        """(seconds, grating changes) through ``wavelengths`` in order, from the first."""
        total, changes = 0.0, 0
        prev = None
        for w in np.asarray(wavelengths, float):
            g, f = choose(self.gratings, w), choose(self.filters, w) if self.filters else None
            if prev is not None:
                pw, pg, pf = prev
                if g != pg:
                    total += self.grating_s
                    changes += 1
                if f is not None and pf is not None and f != pf:
                    steps = abs(f - pf) % 6
                    total += self.filter_step_s * min(steps, 6 - steps)
                if w != pw:
                    total += self.settle_s + abs(w - pw) / (self.slew * 1200.0 / self.LINES.get(g or 1, 1200))
            prev = (w, g, f)
        return float(total), changes


def geometry_groups(angles) -> tuple[np.ndarray, np.ndarray]:
    """(the geometry of each point, the first point of each geometry), geometries in the order
    they first occur."""
    a = np.round(np.asarray(angles, float), 6)
    _, first, inverse = np.unique(a, axis=0, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))              # geometries numbered in order of appearance
    return rank[inverse.reshape(-1)], np.sort(first)


@dataclass(frozen=True)
class SpectralOrder:
    """What `spectral_order` chose and why: the wavelength axis, and each order's estimated
    stage and monochromator time (s) and grating changes."""

    axis: str
    fastest: tuple[float, float, int]
    slowest: tuple[float, float, int]

    def to_dict(self) -> dict:
        return {"wavelength_axis": self.axis,          # plain floats and ints: session.toml's TOML writer
                **{f"{k}_{q}": kind(v) for k, t in (("fastest", self.fastest), ("slowest", self.slowest))
                   for q, v, kind in zip(("stage_s", "monochromator_s", "grating_changes"), t, (float, float, int))}}

    @classmethod
    def from_dict(cls, d) -> "SpectralOrder | None":
        """The choice as session.toml's ``[order]`` records it (`to_dict`); None without one."""
        if not isinstance(d, Mapping) or d.get("wavelength_axis") not in ("fastest", "slowest"):
            return None
        try:
            return cls(d["wavelength_axis"], *(tuple(t(d[f"{k}_{q}"]) for q, t in
                                                     (("stage_s", float), ("monochromator_s", float),
                                                      ("grating_changes", int))) for k in ("fastest", "slowest")))
        except (KeyError, TypeError, ValueError):
            return None

    def line(self) -> str:
        f, s = self.fastest, self.slowest
        changes = lambda n: f"{n} grating change" + ("" if n == 1 else "s")
        return (f"wavelength the {self.axis} axis: as the fastest {f[0] + f[1]:.0f} s (stages {f[0]:.0f} s, "
                f"monochromator {f[1]:.0f} s, {changes(f[2])}), as the slowest {s[0] + s[1]:.0f} s "
                f"(stages {s[0]:.0f} s, monochromator {s[1]:.0f} s, {changes(s[2])})")


def spectral_order(angles, wavelength_nm, stage_deg, settings: Mapping) -> tuple[OrderResult, SpectralOrder]:
    """The visiting order of a spectral plan's points (see the module docstring) and the choice."""
    wl = np.asarray(wavelength_nm, float)
    stage = np.asarray(stage_deg, float)
    geo, first = geometry_groups(angles)
    res = order_moves(stage[first], settings)
    tour = [int(g) for g in res.order]
    chosen = res.stage_deg[geo]                      # each point at its geometry's chosen solution
    members = {g: sorted(np.flatnonzero(geo == g), key=lambda k: wl[k]) for g in range(len(first))}
    fastest = [k for i, g in enumerate(tour) for k in (members[g] if i % 2 == 0 else members[g][::-1])]
    at = {(int(geo[k]), float(wl[k])): k for k in range(len(wl))}
    slowest = [at[(g, w)] for j, w in enumerate(np.unique(wl)) for g in (tour if j % 2 == 0 else tour[::-1])
               if (g, w) in at]
    mono = MonochromatorTimes(settings)
    est = {}
    for name, seq in (("fastest", fastest), ("slowest", slowest)):
        secs, changes = mono.run(wl[seq])
        est[name] = (path_time(chosen[seq], settings, np.zeros(4)), secs, changes)
    axis = min(est, key=lambda k: est[k][0] + est[k][1])
    seq = np.asarray(fastest if axis == "fastest" else slowest, int)
    naive = path_time(stage, settings, np.zeros(4))
    ordered = est[axis][0]
    return OrderResult(seq, chosen, naive, ordered, min(res.bound_s, ordered)), SpectralOrder(axis, est["fastest"],
                                                                                              est["slowest"])


def order_plan(plan, stage_deg, settings: Mapping) -> tuple[OrderResult, dict]:
    """A capture's order of ``plan`` and what to add to session.toml's ``[order]``: `order_moves`
    for a plan without wavelengths; for a spectral plan, the wavelengths checked against the
    monochromator (`check_wavelengths`) and `spectral_order`'s choice."""
    if getattr(plan, "wavelength_nm", None) is None:
        return order_moves(stage_deg, settings), {}
    check_wavelengths(plan.wavelength_nm, settings)
    order, why = spectral_order(plan.angles, plan.wavelength_nm, stage_deg, settings)
    return order, why.to_dict()
