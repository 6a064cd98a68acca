"""Instrument settings: the defaults in ``instrument.toml`` merged with a user's overrides."""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any, Mapping

from .errors import GonioError

__all__ = ["DEFAULT_SETTINGS_PATH", "default_settings", "load_settings", "merge_settings", "AXES"]

DEFAULT_SETTINGS_PATH = Path(__file__).with_name("instrument.toml")
AXES = ("yaw", "tilt", "azimuth", "lamp")   # the order of a stage-angle vector everywhere


def default_settings() -> dict[str, Any]:
    """Return a fresh copy of the default instrument settings (``bench/instrument.toml``)."""
    return _validated(tomllib.loads(DEFAULT_SETTINGS_PATH.read_text()))


def merge_settings(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``base`` updated table by table with ``override`` (one level of tables deep)."""
    out = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = {**out[key], **copy.deepcopy(dict(value))}
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_settings(path: str | Path | None = None) -> dict[str, Any]:
    """Load settings: the defaults, overridden by the tables of the TOML file at ``path``.

    Raises
    ------
    GonioError
        The file is missing or malformed, or a value is invalid.
    """
    if path is None:
        return default_settings()
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise GonioError(f"cannot read settings file {path}: {exc.strerror}; check the path") from None
    try:
        user = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise GonioError(f"settings file {path} is not valid TOML ({exc}); fix the syntax") from None
    return _validated(merge_settings(default_settings(), user), str(path))


def _validated(s: dict[str, Any], where: str = "instrument settings") -> dict[str, Any]:
    """Check the tables the bench relies on; raise a one-line GonioError otherwise."""
    try:
        for name in AXES:
            dev, ax, lo, hi = s["axes"][name]
            if not (int(dev) >= 1 and int(ax) >= 1 and math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"axes.{name}")
            vmax, acc = s["motion"][name]
            if not (vmax > 0 and acc > 0):
                raise ValueError(f"motion.{name}")
        if int(s["axes"]["cycle_dist"]) <= 0:
            raise ValueError("axes.cycle_dist")
        rho = float(s["reference"]["reflectance"])
        if not 0 < rho <= 1.5:
            raise ValueError("reference.reflectance")
        for key in ("width", "height", "pixel_size", "bits"):
            if not s["camera"][key] > 0:
                raise ValueError(f"camera.{key}")
    except (KeyError, TypeError, ValueError) as exc:
        raise GonioError(f"{where}: missing or invalid value {exc}; compare with {DEFAULT_SETTINGS_PATH.name}") from None
    return s
