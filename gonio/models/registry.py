"""The model registry: models by name, each configured by its discrete options."""

from __future__ import annotations

__all__ = ["register", "get", "names"]

_REGISTRY: dict[str, type] = {}


def register(cls):
    """Class decorator: add a :class:`~gonio.models.Model` subclass to the registry under ``cls.name``."""
    _REGISTRY[cls.name] = cls
    return cls


def names():
    """Names of the registered models, sorted."""
    return tuple(sorted(_REGISTRY))


def get(name, **options):
    """Return the model ``name`` configured with discrete ``options``.

    Raises
    ------
    ValueError
        Unknown model name or option.
    """
    try:
        cls = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown model {name!r}; known models: {', '.join(names())}") from None
    return cls(**options)
