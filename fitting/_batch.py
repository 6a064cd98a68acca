"""Fit many datasets (a material library, per-texel data) on Dask.

``fit_batch`` submits the datasets' :func:`~gonio.fitting.fit` calls to a dask.distributed
cluster, a few contiguous datasets per task (:func:`task_chunks`: about four tasks per
worker thread, so small fits do not each pay for a task's round trip): a local one (processes, one thread each: the model kernels hold the GIL) unless
``scheduler`` names an existing one. The local cluster is private to this process: its
scheduler and workers talk TLS with mutual authentication, with a key and self-signed
certificate generated for this run only and kept in memory (``Security.temporary()`` when
the ``cryptography`` package is installed, else the ``openssl`` command), so no other user
or process on the machine can connect to it or run code in a worker; it has no dashboard
unless one is asked for. Where neither can make a certificate, the workers run as threads
of this process (``inproc://``: nothing listens on any socket). Dataset i is fitted with
``rng = numpy.random.default_rng([rng_seed, i])``, so the results equal a serial loop with
the same seeds, whatever the number of workers or the order in which they finish.
Results come back in the order of ``datasets``.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile

import numpy as np

import gonio.models as gm

__all__ = ["fit_batch", "fit_serial", "local_security", "check_workers", "check_scheduler_address",
           "MAX_WORKERS"]

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


def local_cluster(n_workers: int = 2, dashboard_address: str | None = None):
    """A private local cluster (see the module notes); the caller closes it."""
    from dask.distributed import LocalCluster

    import dask

    n_workers = check_workers(n_workers)
    if dashboard_address is not None:
        dashboard_address = check_dashboard_address(dashboard_address)
    security = local_security()
    # Scheduler and workers always start an HTTP server (health, info, JSON routes): without a
    # dashboard they get no routes, and are stopped once the cluster is up (_close_http).
    config = {"distributed.worker.http.routes": []}
    if dashboard_address is None:
        config["distributed.scheduler.http.routes"] = []
    with dask.config.set(config):
        if security is None:
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=False,
                                   dashboard_address=dashboard_address)
        else:
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, protocol="tls://",
                                   host="127.0.0.1", security=security, dashboard_address=dashboard_address)
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


def _one_thread_per_worker():
    """Inside a Dask worker: one Dr.Jit thread. Dask parallelises over datasets; a worker
    process per core each running Dr.Jit's own pool of one thread per core would put twice
    as many busy threads as cores on the machine."""
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return
    import drjit as dr

    if dr.thread_count() != 1:
        dr.set_thread_count(1)


def _fit_one(meas, model_spec, i, rng_seed, fit_kwargs):
    from ._optimise import fit

    _one_thread_per_worker()

    name, options = model_spec
    model = gm.get(name, **options)
    return fit(meas, model, rng=np.random.default_rng([rng_seed, i]), **fit_kwargs)


def _fit_many(metas, model_spec, first, rng_seed, fit_kwargs):
    """Datasets ``first``, ``first + 1``, ... fitted in turn in one task (same seeds as
    :func:`_fit_one`)."""
    return [_fit_one(m, model_spec, first + k, rng_seed, fit_kwargs) for k, m in enumerate(metas)]


def task_chunks(n_datasets: int, n_threads: int, per_thread: int = 4) -> list:
    """Contiguous ``(start, stop)`` ranges of the datasets, one per Dask task: about
    ``per_thread`` tasks per worker thread (enough to even out fits of unequal length), so
    that many small fits travel as a few tasks instead of paying Dask's cost of shipping a
    task and its result (~10-50 ms) each."""
    if n_datasets <= 0:
        return []
    # no worker known yet (a remote scheduler still waiting for them): a task per dataset
    n_tasks = n_datasets if n_threads <= 0 else max(1, min(n_datasets, per_thread * n_threads))
    edges = np.linspace(0, n_datasets, n_tasks + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _spec(model):
    return (model.name, dict(model.options)) if not isinstance(model, tuple) else model


def fit_serial(datasets, model, *, rng_seed: int = 0, **fit_kwargs) -> list:
    """The same fits as :func:`fit_batch`, in this process (the reference for equality)."""
    return [_fit_one(m, _spec(model), i, rng_seed, fit_kwargs) for i, m in enumerate(datasets)]


def fit_batch(datasets, model, *, scheduler: str | None = None, n_workers: int = 2, rng_seed: int = 0,
              dashboard_address: str | None = None, **fit_kwargs) -> list:
    """Fit every dataset in ``datasets`` with ``model`` on a Dask cluster.

    Parameters
    ----------
    datasets : sequence of Measurements
    model
        A gonio model, or ``(name, options)``.
    scheduler : str, optional
        Address of an existing dask.distributed scheduler (``tcp://host:8786``); default: a
        private local cluster of ``n_workers`` single-threaded worker processes (TLS with a
        certificate made for this run), closed afterwards.
    n_workers : int
        1 to :data:`MAX_WORKERS`.
    dashboard_address : str, optional
        Where the local cluster serves its dashboard (e.g. ``127.0.0.1:8787``); default none.
    rng_seed : int
        Dataset i uses ``default_rng([rng_seed, i])``.
    fit_kwargs
        Passed to :func:`~gonio.fitting.fit` (loss, fixed, n_starts, ...).

    Returns
    -------
    list of FitResult, in the order of ``datasets``.
    """
    from dask.distributed import Client

    spec = _spec(model)
    cluster = None
    if scheduler is None:
        cluster = local_cluster(n_workers, dashboard_address)
        try:
            client = Client(cluster, security=cluster.security)
            _close_http(client, keep_scheduler=dashboard_address is not None)
        except BaseException:
            cluster.close()
            raise
    else:
        address = check_scheduler_address(scheduler)
        try:
            client = Client(address, timeout="20s")
        except (TypeError, ValueError) as exc:       # tls:// without certificates in Dask's config
            raise ConnectionError(f"{' '.join(str(exc).split())[:200]}; a tls:// scheduler needs its "
                                  "certificates in Dask's configuration (distributed.comm.tls)") from None
    try:
        datasets = list(datasets)
        chunks = task_chunks(len(datasets), sum(client.nthreads().values()))
        futures = [client.submit(_fit_many, datasets[a:b], spec, a, rng_seed, fit_kwargs, pure=False)
                   for a, b in chunks]
        return [res for part in client.gather(futures) for res in part]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
