"""gonio's allocator settings for fitting processes (gonio.fitting.tune_allocator)."""

import os
import subprocess
import sys

import pytest

from gonio.fitting.batch.malloc import MALLOC_ENV

glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or os.confstr("CS_GNU_LIBC_VERSION") is None,
                           reason="mallopt's settings are glibc's")

# a fit's pattern: temporaries of a few MiB made and dropped in a loop (a 1e5 x 3 float64
# array is 2.4 MB); the page faults of the loop's last 200 rounds, after 20 to settle
_LOOP = """
import resource, sys
import numpy as np
from gonio.fitting import tune_allocator
if sys.argv[1] == "late-env":      # what Dask's nanny does to the process that starts workers
    import os
    from gonio.fitting.batch.malloc import MALLOC_ENV
    os.environ.update(MALLOC_ENV)
tuned = tune_allocator() if sys.argv[1] != "keep" else None
a = np.ones((100_000, 3))
def rounds(n):
    for _ in range(n):
        b = a * 2.0          # 2.4 MB
        c = b + a            # a second one above it on the heap
        del b                # the lower one freed first: the heap's top moves when c goes
        d = np.empty((50_000, 3)); d[:] = 1.0
        del c, d
rounds(20)
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
rounds(200)
print(tuned, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


def _run(mode, env=None):
    full = {k: v for k, v in os.environ.items() if k not in MALLOC_ENV}
    full.update(env or {})
    out = subprocess.run([sys.executable, "-c", _LOOP, mode], capture_output=True, text=True, env=full, timeout=120)
    assert out.returncode == 0, out.stderr
    tuned, faults = out.stdout.split()
    return tuned, int(faults)


@glibc
def test_tuned_allocator_stops_the_page_faults_of_a_fits_temporaries():
    """glibc's defaults hand a freed multi-MiB block back to the kernel (mmap, or the heap's top
    past the trim threshold), so each round faults its pages in again: 200 rounds of 2.4 MB
    temporaries fault in hundreds of thousands of 4 KiB pages (measured 228,000). With gonio's settings the blocks stay on the heap:
    fewer than 200 faults in those 200 rounds (measured 0-3). The same with the settings
    given by the environment (a Dask worker of fit_batch's local cluster), and when they
    were written into ``os.environ`` after the process started (glibc read its environment
    at the start: tune_allocator reads that one, /proc/self/environ)."""
    _, default = _run("keep")
    tuned, faults = _run("tune")
    assert tuned == "True"
    assert default > 50_000, default
    assert faults < 200, faults
    tuned_env, faults_env = _run("tune", env=MALLOC_ENV)
    assert tuned_env == "True" and faults_env < 200, (tuned_env, faults_env)
    # the settings written into os.environ after the start (glibc never saw them): applied
    tuned_late, faults_late = _run("late-env")
    assert tuned_late == "True" and faults_late < 200, (tuned_late, faults_late)


@glibc
def test_a_users_own_allocator_settings_are_kept():
    """MALLOC_TRIM_THRESHOLD_ set by the user to something else: tune_allocator changes nothing
    and says so (False)."""
    tuned, _ = _run("tune", env={"MALLOC_TRIM_THRESHOLD_": "131072"})
    assert tuned == "False"
