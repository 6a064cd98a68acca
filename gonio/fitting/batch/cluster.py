"""The Dask cluster a batch fit runs on: a private local one, or the address of an existing one.

A local cluster is private to this process: TLS with mutual authentication and a key and
certificate made for this run and kept in memory (else worker threads over ``inproc://``), no
dashboard unless asked for, worker processes with Dr.Jit on one thread and gonio's allocator
settings (:func:`worker_environ`). Addresses, worker counts and dashboards a user gives are
checked here (one line each). :mod:`gonio.fitting.batch.dask_batch` runs the fits on it.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import tempfile

import numpy as np

from gonio.fitting.batch.malloc import MALLOC_ENV

__all__ = ["local_security", "local_cluster", "local_client", "check_workers", "check_scheduler_address",
           "check_dashboard_address", "worker_environ", "environ_kept", "MAX_WORKERS", "WORKER_ENV", "QUIET"]

#: the local worker processes' environment: Dr.Jit's pool of one thread (see the module notes)
WORKER_ENV = {"GONIO_THREADS": "1"}

#: Dask's periodic work that only a dashboard shows, slowed or off in a local cluster
#: without one: the workers' statistical profiler (a look at every thread's stack each 10
#: ms), the event-loop health tick (20 ms) and the system monitor (500 ms). Each wakes a
#: worker's event loop, which then takes the GIL from the task's thread; on a machine whose
#: cores are all fitting, it also takes a core. Measured (2026-12-03, 2 cores, 2 workers,
#: 16 roughconductor fits of 1e5 points from files, four calls each, two clusters each way):
#: 0.603-0.623 s a call with Dask's defaults, 0.567-0.604 s without them; the task thread's
#: wall time then equals its CPU time to 2 %.
#: Also slowed, though not only a dashboard's: the memory monitor of each worker and of its
#: nanny (every 100 ms by default: a worker that outgrows its memory limit is now paused or
#: restarted within a second instead of a tenth), the client's refresh of the scheduler's
#: information (every 2 s, now every minute; a batch asks for the workers when it starts),
#: and, off, the scheduler's active memory manager (every 2 s; it drops extra replicas of
#: results, and gonio's tasks make none). Measured (2026-12-03, the same 16 fits, eight calls a
#: cluster, three clusters each way): 0.537-0.539 s best and 0.543-0.549 s median a call,
#: against 0.544-0.551 s and 0.551-0.555 s with the three at Dask's defaults.
QUIET = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "1s",
         "distributed.admin.system-monitor.interval": "10s",
         "distributed.worker.memory.monitor-interval": "1s",
         "distributed.scheduler.active-memory-manager.start": False,
         "distributed.client.scheduler-info-interval": "60s"}

#: at most this many local workers (processes with one thread each; more than the cores is waste)
MAX_WORKERS = max(1, min(256, 4 * (os.cpu_count() or 1)))

_ADDRESS = re.compile(r"^(?:(tcp|tls)://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.\-]{0,252})):(\d{1,5})/?$")


def check_workers(n) -> int:
    """``n`` local workers, 1 <= n <= MAX_WORKERS (ValueError with one line otherwise)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= int(n) <= MAX_WORKERS:
        raise ValueError(f"--workers {n!r}: give a number of local Dask workers from 1 to {MAX_WORKERS} "
                         f"(this machine has {os.cpu_count() or 1} cores)")
    return int(n)


def check_dashboard_address(address: str) -> str:
    """``HOST:PORT`` for the local cluster's dashboard."""
    m = _ADDRESS.match(str(address).strip())
    if not m or m.group(1) or not 0 <= int(m.group(3)) <= 65535:
        raise ValueError(f"--dashboard {str(address)[:80]!r}: give HOST:PORT, e.g. 127.0.0.1:8787")
    return str(address).strip()


def check_scheduler_address(address: str) -> str:
    """A Dask scheduler address ``tcp://HOST:PORT``, ``tls://HOST:PORT`` or ``HOST:PORT``."""
    m = _ADDRESS.match(str(address).strip())
    if not m or not 1 <= int(m.group(3)) <= 65535:
        raise ValueError(f"--scheduler {str(address)[:80]!r} is not a Dask scheduler address; "
                         "give tls://HOST:PORT (or tcp://HOST:PORT), e.g. tls://10.0.0.5:8786")
    return str(address).strip()


def _openssl_pair():
    """(key PEM, certificate PEM) from the ``openssl`` command, or None where there is none."""
    exe = shutil.which("openssl")
    if exe is None:
        return None
    folder = tempfile.mkdtemp(prefix="gonio-dask-")     # mode 0700: the key never is readable by others
    try:
        key, cert = os.path.join(folder, "key.pem"), os.path.join(folder, "cert.pem")
        proc = subprocess.run([exe, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
                               "-nodes", "-keyout", key, "-out", cert, "-days", "2", "-subj", "/CN=dask-internal",
                               "-addext", "subjectAltName=DNS:dask-internal"],
                              stdin=subprocess.DEVNULL, capture_output=True, timeout=60)
        if proc.returncode != 0:
            return None
        with open(key) as fh:
            key_pem = fh.read()
        with open(cert) as fh:
            cert_pem = fh.read()
        return key_pem, cert_pem
    except (OSError, subprocess.SubprocessError):
        return None
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def local_security():
    """A ``distributed.Security`` for a private local cluster (TLS, mutual authentication, a
    fresh in-memory key and certificate), or None where no certificate can be made."""
    from distributed.security import Security

    try:
        return Security.temporary()
    except ImportError:
        pass
    pair = _openssl_pair()
    if pair is None:
        return None
    key, cert = pair
    return Security(require_encryption=True, tls_ca_file=cert,
                    tls_client_key=key, tls_client_cert=cert,
                    tls_scheduler_key=key, tls_scheduler_cert=cert,
                    tls_worker_key=key, tls_worker_cert=cert)


def worker_environ() -> dict:
    """Dask's ``distributed.nanny.pre-spawn-environ`` for the local workers, with gonio's
    allocator settings (:data:`gonio.fitting.batch.malloc.MALLOC_ENV`) in place of Dask's
    ``MALLOC_TRIM_THRESHOLD_`` (65536: Dask sets it so that workers hand freed memory back to
    the OS, which also turns off glibc's adaptive mmap threshold, so every numpy array above
    128 KiB is a fresh mmap whose pages fault in again). Measured, roughconductor fits of 1e5
    points, one Dr.Jit thread: Dask's setting 108-114 ms a fit, glibc's adaptive defaults
    84-89 ms (2026-12-02); 8 fits from files in a task of a 2-worker cluster 0.575-0.59 s of
    the task thread's CPU with the defaults (29,000 page faults in each worker), 0.52-0.53 s
    with gonio's settings (5-8 page faults) (2026-12-03)."""
    import dask

    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    env.update(MALLOC_ENV)
    return env


def local_cluster(n_workers: int = 2, dashboard_address: str | None = None):
    """A private local cluster (see the module notes); the caller closes it."""
    n_workers = check_workers(n_workers)
    if dashboard_address is not None:
        dashboard_address = check_dashboard_address(dashboard_address)
    security = local_security()
    # Scheduler and workers always start an HTTP server (health, info, JSON routes): without a
    # dashboard they get no routes, and are stopped once the cluster is up (_close_http).
    config = {"distributed.worker.http.routes": [], "distributed.nanny.pre-spawn-environ": worker_environ()}
    if dashboard_address is None:
        config["distributed.scheduler.http.routes"] = []
        config.update(QUIET)
    # Dask's nannies write their workers' pre-spawn environment (OMP_NUM_THREADS=1, the
    # allocator's settings) into this process's os.environ before spawning; put it back after
    with environ_kept():
        return _start_local(n_workers, dashboard_address, config, security)


@contextlib.contextmanager
def environ_kept():
    """Put ``os.environ`` back as it was on leaving (for code that starts processes by
    writing their environment into this process's first: Dask's nannies, and
    :func:`gonio.perf.fit_dask`'s plain processes)."""
    saved = dict(os.environ)
    try:
        yield
    finally:
        for key in set(os.environ) - set(saved):
            del os.environ[key]
        for key, value in saved.items():
            if os.environ.get(key) != value:
                os.environ[key] = value


def local_client(cluster, dashboard: bool = False):
    """A client of a :func:`local_cluster` (the caller closes it): not Dask's default client,
    so that it does not change the caller's dask.config (a default client left
    ``scheduler='dask.distributed'`` behind when two were closed out of order, and every later
    xarray ``to_netcdf`` failed); with :data:`QUIET`'s client settings unless ``dashboard``;
    the workers' HTTP listeners (and the scheduler's, without a dashboard) stopped."""
    import dask
    from dask.distributed import Client

    with dask.config.set({} if dashboard else QUIET):
        client = Client(cluster, security=cluster.security, set_as_default=False)
    try:
        _close_http(client, keep_scheduler=dashboard)
    except BaseException:
        client.close()
        raise
    return client


def _start_local(n_workers, dashboard_address, config, security):
    from dask.distributed import LocalCluster

    import dask

    with dask.config.set(config):
        if security is None:
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=False,
                                   dashboard_address=dashboard_address)
        else:
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, protocol="tls://",
                                   host="127.0.0.1", security=security, dashboard_address=dashboard_address,
                                   env=WORKER_ENV)
    return cluster


def _stop_http(dask_worker=None, dask_scheduler=None):
    server = getattr(dask_worker or dask_scheduler, "http_server", None)
    if server is not None:
        server.stop()


def _close_http(client, keep_scheduler: bool) -> None:
    """Stop the HTTP listeners of the workers (and of the scheduler, without a dashboard)."""
    client.run(_stop_http)
    if not keep_scheduler:
        client.run_on_scheduler(_stop_http)


def _in_worker_process() -> bool:
    """True inside a Dask worker that is a process of its own (not a thread of the process
    that called :func:`fit_batch`, whose Dr.Jit pool is left alone)."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return False
    return not str(getattr(worker, "address", "")).startswith("inproc://")


def _one_thread_per_worker():
    """Inside a Dask worker process: one Dr.Jit thread (the local workers already have it
    from ``GONIO_THREADS``; this covers the workers of an existing scheduler). Dask
    parallelises over datasets; a worker process per core each running Dr.Jit's own pool of
    one thread per core would put twice as many busy threads as cores on the machine."""
    if not _in_worker_process():
        return
    import drjit as dr

    if dr.thread_count() != 1:
        dr.set_thread_count(1)
