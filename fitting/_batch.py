"""Fit many datasets (a material library, per-texel data) on Dask.

``fit_batch`` submits one :func:`~gonio.fitting.fit` per dataset to a dask.distributed
cluster: a local one (processes, one thread each: the model kernels hold the GIL) unless
``scheduler`` names an existing one. Dataset i is fitted with
``rng = numpy.random.default_rng([rng_seed, i])``, so the results equal a serial loop with
the same seeds, whatever the number of workers or the order in which they finish.
Results come back in the order of ``datasets``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_batch", "fit_serial"]


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
    import gonio.models as gm

    from ._optimise import fit

    _one_thread_per_worker()

    name, options = model_spec
    model = gm.get(name, **options)
    return fit(meas, model, rng=np.random.default_rng([rng_seed, i]), **fit_kwargs)


def _spec(model):
    return (model.name, dict(model.options)) if not isinstance(model, tuple) else model


def fit_serial(datasets, model, *, rng_seed: int = 0, **fit_kwargs) -> list:
    """The same fits as :func:`fit_batch`, in this process (the reference for equality)."""
    return [_fit_one(m, _spec(model), i, rng_seed, fit_kwargs) for i, m in enumerate(datasets)]


def fit_batch(datasets, model, *, scheduler: str | None = None, n_workers: int = 2, rng_seed: int = 0,
              **fit_kwargs) -> list:
    """Fit every dataset in ``datasets`` with ``model`` on a Dask cluster.

    Parameters
    ----------
    datasets : sequence of Measurements
    model
        A gonio model, or ``(name, options)``.
    scheduler : str, optional
        Address of an existing dask.distributed scheduler (``tcp://host:8786``); default: a
        local cluster of ``n_workers`` single-threaded worker processes, closed afterwards.
    rng_seed : int
        Dataset i uses ``default_rng([rng_seed, i])``.
    fit_kwargs
        Passed to :func:`~gonio.fitting.fit` (loss, fixed, n_starts, ...).

    Returns
    -------
    list of FitResult, in the order of ``datasets``.
    """
    from dask.distributed import Client, LocalCluster

    spec = _spec(model)
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        futures = [client.submit(_fit_one, m, spec, i, rng_seed, fit_kwargs, pure=False)
                   for i, m in enumerate(datasets)]
        return client.gather(futures)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
