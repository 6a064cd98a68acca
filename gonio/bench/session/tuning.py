"""A spectral session's wavelengths: the part of a run (`gonio.bench.session.run._Session`)
that sets the monochromator before each point's bracket.

A plan with ``wavelength_nm`` (`gonio.bench.plan.spectral`) is measured one (geometry,
wavelength) point at a time: before the bracket the monochromator goes to the point's
wavelength (grating and order-sorting filter chosen by its driver) and the power meter is set
to it, so the monitor reads the beam at that wavelength. The monitor's session reference is
kept per wavelength, journalled the first time (``p_ref_nm`` events, JSON ``{"nm", "p"}``) so a
resumed session compares its readings with the same references; each point's row records the
wavelength the monochromator read back (``detail["wavelength_nm"]``). Without a monochromator the
reference is one reading with the lamp on (`_p_ref`, the ``p_ref`` event).
"""

from __future__ import annotations

import json

import numpy as np

from gonio.core.errors import DeviceError, SessionError

__all__ = ["Tuning"]


class Tuning:
    """The wavelength of a spectral session's points (a mixin of the run's session)."""

    def _init_tuning(self, plan, journal) -> None:
        wl = plan.wavelength_nm
        self.wavelength = None if wl is None else np.asarray(wl, float)
        self.at_nm: float | None = None           # the wavelength set now
        self.read_nm: float | None = None         # what the monochromator read back there
        self.p_refs = {float(v["nm"]): float(v["p"]) for v in
                       (json.loads(text) for _, kind, text in journal.events() if kind == "p_ref_nm")}

    def _light_on(self) -> None:
        """With the lamp on: the monitor's reference (`_p_ref`); for a spectral plan the
        monochromator's shutter opened and its reference at the first point's wavelength."""
        if self.wavelength is None:
            self.p_ref = self._p_ref()
            return
        if getattr(self.bench, "monochromator", None) is None:
            raise SessionError(f"{self.folder}: the plan is spectral; give the monochromator's port")
        self.bench.monochromator.shutter(True)
        self._tune(self._first_todo()[0])

    def _p_ref(self) -> float:
        """The monitor's session reference with the lamp on (white light), journalled once."""
        known = self.journal.first_event("p_ref")       # a resumed session keeps its reference
        if known is not None:
            return float(known)
        p = self.bench.meter.power()
        if not p > 0:
            raise DeviceError(f"the monitor reads {p:g} W with the lamp on; check the LED and the meter, "
                              "then resume the session")
        self.journal.event("p_ref", repr(p))
        return p

    def _tuned(self) -> dict:
        """What a point's journal row adds: ``wavelength_nm`` read back (spectral plans), else nothing."""
        return {} if self.wavelength is None else {"wavelength_nm": float(self.read_nm)}

    def _tune(self, idx: int) -> None:
        """A spectral plan: the monochromator to point ``idx``'s wavelength, the meter set to it,
        the monitor's reference there (journalled the first time, ``p_ref_nm``); nothing otherwise."""
        if self.wavelength is None or float(self.wavelength[idx]) == self.at_nm:
            return
        nm, b = float(self.wavelength[idx]), self.bench
        self.read_nm = b.monochromator.go_to(nm)
        b.meter.configure(nm, int(self.settings.get("meter", {}).get("averaging", 10)))
        self.at_nm = nm
        if nm not in self.p_refs:
            p = b.meter.power()
            if not p > 0:
                raise DeviceError(f"the monitor reads {p:g} W at {nm:g} nm with the lamp on; check the source, the "
                                  "monochromator's shutter and the meter, then resume the session")
            self.journal.event("p_ref_nm", json.dumps({"nm": nm, "p": p}))
            self.p_refs[nm] = p
        self.p_ref = self.p_refs[nm]
