"""Test doubles for the bench's serial drivers.

``expect://NAME`` (registered by tests/bench/conftest.py) opens a port that plays a script
registered with `expect`: each line the driver writes must equal the next expected line,
byte for byte (pymeasure's ``expected_protocol`` idea), and the scripted reply is then
readable. A reply of ``None`` is silence (the driver's read times out at once); a callable
reply is called with the written bytes (to write a file, say) and returns the reply.
"""

from __future__ import annotations

SCRIPTS: dict[str, "Exchange"] = {}


class Exchange:
    """An expected conversation: a list of ``(bytes written, bytes replied or None)``."""

    def __init__(self, pairs):
        self.pairs = [(w if isinstance(w, bytes) else w.encode(),
                       r if (r is None or isinstance(r, bytes) or callable(r)) else r.encode())
                      for w, r in pairs]
        self.i = 0
        self.opened = 0
        self.closed = 0

    def next(self, written: bytes):
        assert self.i < len(self.pairs), f"unexpected extra write {written!r}"
        want, reply = self.pairs[self.i]
        assert written == want, f"exchange {self.i}: wrote {written!r}, expected {want!r}"
        self.i += 1
        if callable(reply):
            reply = reply(written)
            reply = reply.encode() if isinstance(reply, str) else reply
        return reply

    def done(self) -> bool:
        return self.i == len(self.pairs)


def expect(name: str, pairs) -> Exchange:
    """Register the script for ``expect://name`` and return it."""
    SCRIPTS[name] = Exchange(pairs)
    return SCRIPTS[name]
