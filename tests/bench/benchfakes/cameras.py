"""A camera double for the stop tests: the simulated camera that presses Ctrl-C."""

from __future__ import annotations

import os
import signal

from gonio.bench.drivers.camera import SimCamera


class InterruptingCamera:
    """The simulated camera; after ``after`` exposures it sends this process SIGINT
    ``presses`` times (once: finish the point and stop; twice: stop now), and it calls
    ``hook(n, path)`` before every exposure when given one."""

    def __init__(self, url, after=0, hook=None, presses=1):
        self.cam, self.after, self.n, self.hook, self.presses = SimCamera(url), after, 0, hook, presses

    def expose(self, seconds, path):
        self.n += 1
        if self.hook is not None:
            self.hook(self.n, path)
        if self.n == self.after:
            for _ in range(self.presses):
                os.kill(os.getpid(), signal.SIGINT)
        return self.cam.expose(seconds, path)

    def flat(self, seconds, path):
        return self.cam.flat(seconds, path)

    def close(self):
        self.cam.close()
