"""What flakepaint's and gratingpaint's numpy evaluation reuses between the calls of one fit.

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
import threading

import numpy as np

from gonio.core.geometry import half_vector

__all__ = ["MAX_POINTS", "Geometry", "geometry", "memo", "values"]

#: direction sets of up to this many pairs are remembered (a screen's 2000, a file's ~8000)
MAX_POINTS = 20_000
#: direction sets remembered, most recent first; and shapes remembered per direction set
GEOMETRIES = 4
SHAPES = 24

_lock = threading.Lock()
_geometries: list = []


class Geometry:
    """The per-pair quantities of the lobes (names as in flakepaint and gratingpaint)."""

    def __init__(self, wi, wo):
        self.wi, self.wo = wi, wo
        wm, valid = half_vector(wi, wo)
        self.wm, self.valid = wm, valid
        self.ci, self.co = wi[:, 2], wo[:, 2]
        self.di = np.einsum("ij,ij->i", wi, wm)
        self.do = np.einsum("ij,ij->i", wo, wm)
        cc = wi[:, 2] * wo[:, 2]
        self.up = ((wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)).astype(float)[:, None]
        # the half-vector lobes (flakepaint.half_vector_lobe)
        ok = (valid & (cc > 0.0) & (wm[:, 2] > 0.0))[:, None]
        self.lobe_ok = ok
        self.c2 = np.where(ok[:, 0], wm[:, 2] ** 2, 1.0)[:, None]
        self.t2 = (wm[:, 0] ** 2 + wm[:, 1] ** 2)[:, None] / self.c2
        self.cos_d = 0.5 * (self.di + self.do)
        self.grazing = (1.0 - np.clip(self.cos_d, 0.0, 1.0))[:, None]
        self.logcc = np.log(np.where(ok[:, 0], cc, 1.0))[:, None]
        # the clear coat (flakepaint._coat)
        self.den = 4.0 * self.ci * self.co
        self.coat_ok = valid & (self.den > 0.0)
        # the rings (gratingpaint.GratingPaint._q_shape)
        self.q = np.hypot(wi[:, 0] + wo[:, 0], wi[:, 1] + wo[:, 1])
        self.q_ok = (cc > 0.0)[:, None]
        self.q_logcc = np.log(np.where(self.q_ok[:, 0], cc, 1.0))[:, None]
        for v in vars(self).values():
            if isinstance(v, np.ndarray):
                v.setflags(write=False)
        self.shapes = collections.OrderedDict()


def geometry(wi, wo) -> Geometry:
    """The :class:`Geometry` of float64 (N, 3) directions ``wi``, ``wo``, remembered where N <=
    :data:`MAX_POINTS` (a copy of the directions kept to compare), else computed afresh."""
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
    g = Geometry(np.array(wi), np.array(wo))
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
