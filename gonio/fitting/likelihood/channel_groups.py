"""A spectral fit's f_r from the compiled three-channel kernels, wavelengths in groups of three.

The compiled kernels (:mod:`gonio.models.fast`) hold three channels; a spectral measurement
holds one per wavelength (Cornell's ASTM files: 31). Every per-channel parameter of a model
whose :class:`~gonio.models.structure.Structure` declares no coupling acts on its own channel
only, so f_r at C channels is the kernel's f_r at consecutive groups of three channels: the
per-channel parameters sliced to the group's channels, the shared ones as they are. The last
group overlaps the one before it where C is not a multiple of three (its repeated columns are
dropped), and fewer than three channels repeat the last one. The exact derivatives come the
same way, so a Levenberg-Marquardt step on C channels costs ceil(C / 3) kernel calls where the
numpy reference needed one evaluation per parameter. Models that couple channels (principled's
base colour, through its luminance) are not grouped.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ChannelGroups", "channel_groups", "groupable"]


def channel_groups(n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The groups of three channel indices that cover ``n`` channels, each with the channels
    it writes and the group's columns they come from: ``[(index, into, cols), ...]``."""
    n = int(n)
    if n < 1:
        raise ValueError(f"{n} channels: a measurement has at least one")
    if n < 3:
        idx = np.minimum(np.arange(3), n - 1)
        return [(idx, np.arange(n), np.arange(n))]
    out, start = [], 0
    while start < n:
        first = min(start, n - 3)
        idx = np.arange(first, first + 3)
        into = np.arange(start, first + 3)
        out.append((idx, into, into - first))
        start = first + 3
    return out


def groupable(model) -> bool:
    """True when every per-channel parameter of ``model`` acts on its own channel only (no
    declared ``structure.coupled``), so its f_r may be evaluated three channels at a time."""
    return not tuple(getattr(model.structure, "coupled", ()) or ())


class ChannelGroups:
    """f_r and its Jacobian at ``n_channels`` channels from a three-channel evaluator.

    Parameters
    ----------
    model
        The model; its per-channel parameters are sliced to each group's channels.
    three
        A :class:`gonio.fitting.likelihood.problem.Evaluator` of ``model`` at three channels
        on the same directions (its compiled path).
    n_channels : int
        The measurement's channels.
    """

    def __init__(self, model, three, n_channels: int):
        self.model, self.three, self.n = model, three, int(n_channels)
        self.groups = channel_groups(self.n)
        self.per_channel = {p.name for p in model.parameters if p.per_channel}

    def _slice(self, params, idx):
        return {k: (np.asarray(v, float)[idx] if k in self.per_channel else v) for k, v in params.items()}

    def _check(self, params):
        for k in self.per_channel:
            v = np.asarray(params.get(k, ()), float)
            if v.shape != (self.n,):
                raise ValueError(f"{self.model.name}: {k} has shape {v.shape}, not one value per channel ({self.n})")

    def eval(self, params) -> np.ndarray:
        """f_r (N, n_channels)."""
        self._check(params)
        out = None
        for idx, into, cols in self.groups:
            f = np.asarray(self.three(self._slice(params, idx)), np.float64)
            if out is None:
                out = np.empty((f.shape[0], self.n))
            out[:, into] = f[:, cols]
        return out

    def jacobian(self, params):
        """(f_r, {parameter: (N, n_channels)}) as :func:`gonio.models.fast.jacobian` gives them
        at three channels (a per-channel parameter's column c: d f_r[c] / d p[c]), or None
        where the three-channel evaluator has no exact derivatives."""
        self._check(params)
        f = J = None
        for idx, into, cols in self.groups:
            out = self.three.jacobian(self._slice(params, idx))
            if out is None:
                return None
            f3, J3 = out
            if f is None:
                f = np.empty((np.shape(f3)[0], self.n))
                J = {k: np.empty_like(f) for k in J3}
            f[:, into] = np.asarray(f3)[:, cols]
            for k, v in J3.items():
                J[k][:, into] = np.asarray(v)[:, cols]
        return f, J
