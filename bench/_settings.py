"""Instrument settings: the defaults in ``instrument.toml`` merged with a user's overrides."""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any, Mapping

from .errors import GonioError

__all__ = ["DEFAULT_SETTINGS_PATH", "default_settings", "load_settings", "merge_settings", "validate_settings", "AXES"]

DEFAULT_SETTINGS_PATH = Path(__file__).with_name("instrument.toml")
AXES = ("yaw", "tilt", "azimuth", "lamp")   # the order of a stage-angle vector everywhere


def default_settings() -> dict[str, Any]:
    """Return a fresh copy of the default instrument settings (``bench/instrument.toml``)."""
    return validate_settings(tomllib.loads(DEFAULT_SETTINGS_PATH.read_text()))


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
    except UnicodeDecodeError:
        raise GonioError(f"settings file {path} is not UTF-8 text; give a settings TOML file") from None
    try:
        user = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise GonioError(f"settings file {path} is not valid TOML ({exc}); fix the syntax") from None
    return validate_settings(merge_settings(default_settings(), user), str(path))


def validate_settings(s: dict[str, Any], where: str = "instrument settings") -> dict[str, Any]:
    """Check the tables the bench relies on; raise a one-line GonioError naming the bad key."""
    def bad(key: str) -> GonioError:
        return GonioError(f"{where}: missing or invalid {key}; compare with {DEFAULT_SETTINGS_PATH.name}")

    def num(key: str, value, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad(key)
        if positive and not value > 0:
            raise bad(key)
        return float(value)

    try:
        for name in AXES:
            key = f"axes.{name}"
            dev, ax, lo, hi = s["axes"][name]
            if not (int(dev) >= 1 and int(ax) >= 1 and num(key, lo) < num(key, hi)):
                raise bad(key)
            key = f"motion.{name}"
            vmax, acc = s["motion"][name]
            num(key, vmax, True), num(key, acc, True)
        num("axes.cycle_dist", s["axes"]["cycle_dist"], True)
        rho = s["reference"]["reflectance"]
        rho = rho if isinstance(rho, list) else [rho]
        if len(rho) not in (1, 3) or not all(0 < num("reference.reflectance", r) <= 1.5 for r in rho):
            raise bad("reference.reflectance")
        for key in ("width", "height", "pixel_size", "bits"):
            num(f"camera.{key}", s["camera"][key], True)
    except KeyError as exc:
        raise bad(str(exc.args[0])) from None
    except (TypeError, ValueError):
        raise bad("[axes] or [motion] entry (lists of numbers)") from None
    return s
