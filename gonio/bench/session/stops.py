"""The operator's steps of a session with transmitted points, and who performs them.

Moving the camera between the detector arm's front and rear stops, and taking the sample out
of the holder for the open-beam frame and putting it back, are done by hand on the bench. The
session asks for each (`gonio.bench.session.rear`) through an operator: `TwinOperator` is the
simulated instrument's twin, which performs them on the instrument object
(`gonio.sim.Instrument`'s ``detector`` and ``holder_open``); `PromptOperator` asks on a
terminal and waits for Enter; `RefusingOperator` (no terminal: a script) stops the session
resumably with one line saying what to do. `operator_for` picks one for a bench.
"""

from __future__ import annotations

import sys
from typing import Callable, Protocol

from gonio.core.errors import SessionError

__all__ = ["STEPS", "Operator", "TwinOperator", "PromptOperator", "RefusingOperator", "operator_for"]

#: step -> (what the operator is asked to do, the journalled state it leaves: (what, value))
STEPS = {
    "rear_stop": ("move the camera to the detector arm's rear stop (transmission)", ("stop", "rear")),
    "front_stop": ("move the camera to the detector arm's front stop (reflection)", ("stop", "front")),
    "sample_out": ("take the sample out of the holder, leaving its aperture empty, for the open-beam frame",
                   ("sample", "out")),
    "sample_in": ("put the sample back in the holder", ("sample", "in")),
}


class Operator(Protocol):
    """Performs (or confirms) one of `STEPS`; raises `SessionError` to stop the session."""

    name: str

    def perform(self, step: str) -> None: ...


class TwinOperator:
    """The simulated instrument's twin: it does what an operator would, on the instrument."""

    name = "simulator"

    def __init__(self, inst):
        self.inst = inst

    def perform(self, step: str) -> None:
        what, value = STEPS[step][1]
        with self.inst.lock:
            if what == "stop":
                self.inst.detector = value
            else:
                self.inst.holder_open = value == "out"


class PromptOperator:
    """Asks on a terminal; Enter confirms the step done, ``q`` (or end of input) stops the
    session resumably."""

    name = "operator"

    def __init__(self, ask: Callable[[str], str] = input, folder=None):
        self.ask = ask
        self.folder = folder

    def perform(self, step: str) -> None:
        try:
            got = self.ask(f"gonio: {STEPS[step][0]}; press Enter when done (q to stop): ")
        except EOFError:
            got = "q"
        if got.strip().lower().startswith("q"):
            raise SessionError(f"stopped before the operator step: {STEPS[step][0]}; do it, then resume with "
                               f"`gonio capture --resume {self.folder}`")


class RefusingOperator:
    """No one to ask (no terminal): one line saying what to do."""

    name = "none"

    def __init__(self, folder=None):
        self.folder = folder

    def perform(self, step: str) -> None:
        raise SessionError(f"the session needs the operator to {STEPS[step][0]}, and no terminal is there to ask; "
                           f"resume it on a terminal (`gonio capture --resume {self.folder}`), which asks for "
                           "each step and waits")


def operator_for(bench, folder, given: Operator | None = None) -> Operator:
    """``given``, else the twin of a simulated bench (its camera on ``sim://NAME/camera``), else
    a prompt on a terminal, else `RefusingOperator`."""
    if given is not None:
        return given
    url = str(getattr(bench.camera, "port_url", "") or "")
    if url.startswith("sim://"):
        from gonio.sim.instrument import lookup

        try:
            return TwinOperator(lookup(url[len("sim://"):].split("/", 1)[0]))
        except KeyError:
            pass
    if sys.stdin is not None and sys.stdin.isatty():
        return PromptOperator(folder=folder)
    return RefusingOperator(folder)
