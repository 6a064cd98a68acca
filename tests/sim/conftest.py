import itertools

import pytest

import gonio.sim as gs

_names = itertools.count()


@pytest.fixture
def make():
    """Factory of registered instruments with unique names; unregistered afterwards."""
    made = []

    def _make(**kw):
        kw.setdefault("seed", 1)
        inst = gs.Instrument(**kw).register(f"t{next(_names)}")
        made.append(inst)
        return inst

    yield _make
    for inst in made:
        inst.unregister()
