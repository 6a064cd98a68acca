"""What flakepaint's and gratingpaint's numpy evaluation (and tabulated's Jacobian) reuses
between the calls of one fit.

A fit evaluates f_r hundreds of times at the same directions: their half vector, its angles,
cos_i cos_o and q are computed once (:func:`geometry`). Most calls that change no spread
(the affine probes and linear solves of gonio.fitting.likelihood.problem change only the
colours, in which f_r is linear) reuse the lobe shapes themselves (:func:`memo`). Both are
keyed on content (the directions compared value for value; the spreads by their bytes),
hold a few entries, up to :data:`MAX_POINTS` pairs, and hand out read-only arrays; a model's
results are the same numbers, bit for bit, as computed afresh.
"""

from __future__ import annotations

import collections
import functools
import threading

import numpy as np

from gonio.core.geometry import half_vector

__all__ = ["MAX_POINTS", "Geometry", "geometry", "memo", "values"]

#: direction sets of up to this many pairs are remembered (a screen's 2000, a file's ~8000)
MAX_POINTS = 20_000
#: direction sets remembered, most recent first; and shapes remembered per direction set (vch's
#: screen and ring refinements: 4619 of 6477 lookups found with 6, 4626 with 24, 667 with 2). At
#: most about GEOMETRIES * SHAPES * 8 arrays of (N, 3): 120 MB at 20,000 pairs, 12 MB at 2,000
GEOMETRIES = 4
SHAPES = 8

_lock = threading.Lock()
_geometries: list = []


class Geometry:
    """The per-pair quantities of the lobes (names as in flakepaint and gratingpaint), each
    computed on first use (a direction set seen once, an albedo's nodes, pays only for its own)."""

    def __init__(self, wi, wo):
        self.wi, self.wo = wi, wo
        self.ci, self.co = wi[:, 2], wo[:, 2]
        self.shapes = collections.OrderedDict()

    def _ro(self, *arrays):
        for v in arrays:
            v.setflags(write=False)
        return arrays if len(arrays) > 1 else arrays[0]

    @functools.cached_property
    def _half(self):
        return self._ro(*half_vector(self.wi, self.wo))

    @property
    def wm(self):
        return self._half[0]

    @property
    def valid(self):
        return self._half[1]

    @functools.cached_property
    def di(self):
        return self._ro(np.einsum("ij,ij->i", self.wi, self.wm))

    @functools.cached_property
    def do(self):
        return self._ro(np.einsum("ij,ij->i", self.wo, self.wm))

    @functools.cached_property
    def cc(self):
        return self._ro(self.wi[:, 2] * self.wo[:, 2])

    @functools.cached_property
    def up(self):
        return self._ro(((self.wi[:, 2] > 0.0) & (self.wo[:, 2] > 0.0)).astype(float)[:, None])

    # the half-vector lobes (flakepaint.half_vector_lobe)
    @functools.cached_property
    def lobe_ok(self):
        return self._ro((self.valid & (self.cc > 0.0) & (self.wm[:, 2] > 0.0))[:, None])

    @functools.cached_property
    def c2(self):
        return self._ro(np.where(self.lobe_ok[:, 0], self.wm[:, 2] ** 2, 1.0)[:, None])

    @functools.cached_property
    def t2(self):
        return self._ro((self.wm[:, 0] ** 2 + self.wm[:, 1] ** 2)[:, None] / self.c2)

    @functools.cached_property
    def cos_d(self):
        return self._ro(0.5 * (self.di + self.do))

    @functools.cached_property
    def grazing(self):
        return self._ro((1.0 - np.clip(self.cos_d, 0.0, 1.0))[:, None])

    @functools.cached_property
    def logcc(self):
        return self._ro(np.log(np.where(self.lobe_ok[:, 0], self.cc, 1.0))[:, None])

    # the clear coat (flakepaint._coat)
    @functools.cached_property
    def den(self):
        return self._ro(4.0 * self.ci * self.co)

    @functools.cached_property
    def coat_ok(self):
        return self._ro(self.valid & (self.den > 0.0))

    # the rings (gratingpaint.GratingPaint._q_shape)
    @functools.cached_property
    def q(self):
        return self._ro(np.hypot(self.wi[:, 0] + self.wo[:, 0], self.wi[:, 1] + self.wo[:, 1]))

    @functools.cached_property
    def q_ok(self):
        return self._ro((self.cc > 0.0)[:, None])

    @functools.cached_property
    def q_logcc(self):
        return self._ro(np.log(np.where(self.q_ok[:, 0], self.cc, 1.0))[:, None])


def geometry(wi, wo) -> Geometry:
    """The :class:`Geometry` of float64 (N, 3) directions ``wi``, ``wo``, remembered where N <=
    :data:`MAX_POINTS` (a copy of the directions kept to compare), else computed afresh."""
    with _lock:
        for g in _geometries:   # a remembered set's own (read-only) arrays, handed back in
            if wi is g.wi and wo is g.wo:
                return g
    wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
    n = wi.shape[0]
    if n > MAX_POINTS or wi.shape != wo.shape:
        return Geometry(wi, wo)
    with _lock:
        for k, g in enumerate(_geometries):
            if g.wi.shape == wi.shape and np.array_equal(g.wi, wi) and np.array_equal(g.wo, wo):
                if k:
                    _geometries.insert(0, _geometries.pop(k))
                return g
    wi, wo = np.array(wi), np.array(wo)
    wi.setflags(write=False)
    wo.setflags(write=False)
    g = Geometry(wi, wo)
    with _lock:
        _geometries.insert(0, g)
        del _geometries[GEOMETRIES:]
    return g


def values(p, names) -> tuple:
    """The bytes of parameters ``names`` of ``p`` (a memo key's part)."""
    return tuple(np.asarray(p[n], dtype=np.float64).tobytes() for n in names)


def memo(geom: Geometry, key: tuple, make):
    """``make()`` remembered under ``key`` for the directions of ``geom`` (its arrays read-only)."""
    with _lock:
        hit = geom.shapes.get(key)
        if hit is not None:
            geom.shapes.move_to_end(key)
            return hit
    out = make()
    _freeze(out)
    with _lock:
        geom.shapes[key] = out
        while len(geom.shapes) > SHAPES:
            geom.shapes.popitem(last=False)
    return out


def _freeze(out):
    if isinstance(out, np.ndarray):
        out.setflags(write=False)
    elif isinstance(out, tuple):
        for v in out:
            _freeze(v)
