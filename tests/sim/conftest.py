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


@pytest.fixture
def served(tmp_path):
    """Factory of simulated instruments served on pseudo-terminals (``gonio sim serve`` without
    blocking), each in a link folder of its own; stopped afterwards. ``clock``: instant unless
    given."""
    servers = []

    def _serve(clock="instant", **kw):
        srv = gs.serve(seed=1, clock=clock, link_dir=str(tmp_path / f"p{len(servers)}"), block=False, echo=None, **kw)
        servers.append(srv)
        return srv

    yield _serve
    for srv in servers:
        srv.stop()
