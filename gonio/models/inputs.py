"""What every evaluation path checks first: the directions' precision and shapes, and the
validated parameters (shared by :meth:`gonio.models.Model.eval` and the compiled engine)."""

from __future__ import annotations

import numpy as np

from gonio.core.geometry import as_directions

__all__ = ["eval_dtype", "eval_inputs"]


def eval_dtype(wi, wo):
    """The precision of an evaluation on these directions, as numpy's arithmetic would give
    it: float32 when both are float32 arrays (or numpy float32 scalars), float64 otherwise
    (float64, mixed float32 and float64, integers, float16, lists: promoted to float64)."""
    f32 = np.dtype(np.float32)
    return f32 if getattr(wi, "dtype", None) == f32 and getattr(wo, "dtype", None) == f32 else np.dtype(np.float64)


def eval_inputs(model, wi, wo, params, dtype=np.float64):
    """What every evaluation path checks first: directions as C-contiguous (N, 3) arrays of
    type ``dtype`` (float64 unless told) and one shape, and the validated parameters.
    Returns ``(wi, wo, params)``."""
    wi = as_directions(wi, "wi", dtype)
    wo = as_directions(wo, "wo", dtype)
    if wi.shape != wo.shape:
        raise ValueError(f"wi and wo must have the same shape, got {wi.shape} and {wo.shape}")
    return wi, wo, model.validate(params)
