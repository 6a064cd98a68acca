"""Fit many datasets (a material library, per-texel data) on Dask.

``fit_batch`` runs each dataset's fit (:mod:`gonio.fitting.pipeline`, as `gonio fit`) on a dask.distributed
cluster: a local one (worker processes with one thread each) unless ``scheduler`` names an
existing one or ``client`` is given. A dataset may be given as Measurements or as a loader (a
function of no arguments that returns them, e.g. ``functools.partial(load_dataset, path)``),
called in the worker that fits it. Results come back in the order of ``datasets``.

Every dataset is fitted with ``rng = numpy.random.default_rng(rng_seed)``, so the results
equal single fits with that seed, whatever the number of workers or the order in which
they finish (bit for bit when that loop also runs Dr.Jit on one thread). The local cluster is
private to this process: TLS with mutual authentication and a certificate made for this run
(else worker threads over ``inproc://``), no dashboard unless one is asked for, and a private
temporary folder that is removed when the batch ends.
"""

# How the work is spread (measurements behind it: docs/performance.md,
# gonio.fitting.batch.dask_batch):
# - Each worker process runs Dr.Jit's kernels on one thread (GONIO_THREADS=1 in the local
#   workers' environment, and _one_thread_per_worker in any worker process): Dask parallelises
#   over datasets, and a worker per core each running Dr.Jit's own pool of a thread per core
#   would put twice as many busy threads as cores on the machine.
# - A loader's data never travels through Dask. Measurements given as they are reach worker
#   processes of a local cluster (this process's LocalCluster) through files: each written
#   once to the private folder, while the workers start on the first ones, and mapped by the
#   worker that fits it (gonio.fitting.batch.handoff). To workers elsewhere, or where the files
#   cannot be written (a full disk: with a warning), they travel once, straight from this
#   process to the workers (client.scatter, one object per task), never inside the task graph
#   (which the scheduler would hold and forward).
# - On this process's local workers a task per worker thread takes the datasets one at a time,
#   each claiming the next one not yet taken (_run_claimed: a file created with O_EXCL in the
#   batch's private folder), so the workers finish within one fit of each other whatever the
#   fits' lengths, and Dask ships a task and a result per worker thread, not per chunk.
#   Elsewhere contiguous datasets share a task (task_chunks): large tasks first and ever
#   smaller ones after them (factoring), so that the workers finish within about one fit of
#   each other; a task holds MIN_TASK_S (~50 ms) of fitting or more where the fits' costs are
#   known, instead of paying Dask's cost of shipping a task and its result for each small fit.
# - The workers start with gonio's allocator settings (worker_environ,
#   gonio.fitting.batch.malloc: a fit's multi-MiB temporaries stay on the heap), and without a
#   dashboard Dask's periodic work that only a dashboard shows is off or slowed (QUIET); this
#   process's os.environ, which Dask's nannies write their workers' environment into, is put
#   back.
# - Every worker traces and compiles the model's kernels once, before the timed fits, on a
#   slice of the first dataset (_warm_worker, once per worker, model and fit options), so no
#   task pays for a first call.
# Security: the batch's folder of handoff files and claims is tempfile.mkdtemp, mode 0700. The
# key and self-signed certificate are generated for this run only and kept in memory
# (Security.temporary() when the cryptography package is installed, else the openssl
# command), so no other user or process on the machine can connect to the cluster or run code
# in a worker. With inproc:// nothing listens on any socket, and Dr.Jit's pool is this
# process's, left as it is.
# Reproducibility: with several Dr.Jit threads the partial sums of a reduction are combined in
# the order the threads finish them, so only a one-thread serial loop matches bit for bit.

from __future__ import annotations

import numpy as np

import gonio.models as gm
from gonio.fitting.batch.cluster import (  # noqa: F401  (re-exported: a batch's public face)
    MAX_WORKERS, QUIET, WORKER_ENV, _close_http, _in_worker_process, _one_thread_per_worker, check_dashboard_address,
    check_scheduler_address, check_workers, environ_kept, local_client, local_cluster, local_security,
    worker_environ)

__all__ = ["fit_batch", "fit_serial", "task_chunks", "fit_cost", "fit_many", "model_spec_of",
           # the cluster's (gonio.fitting.batch.cluster), re-exported
           "local_security", "local_cluster", "local_client", "check_workers", "check_scheduler_address",
           "check_dashboard_address", "MAX_WORKERS", "WORKER_ENV"]



def _load(meas):
    """A dataset as Measurements or FitInput: ``meas`` itself, or what the loader ``meas()`` returns."""
    return meas() if callable(meas) else meas


def _points(data) -> int:
    from gonio.fitting.pipeline import as_fit_input

    return as_fit_input(data).meas.wi.shape[0]


def _fit_one(meas, model_spec, i, rng_seed, fit_kwargs):
    """Dataset ``i``'s fit as `gonio fit` fits it (:func:`gonio.fitting.pipeline.fit_measurements`:
    the model resolved from ``(name, options)``, one candidate per declared distribution the
    options leave open; starts from ``default_rng(rng_seed)``, as a single fit with that seed);
    with fit options beyond the loss (``fixed``, ``n_starts``, ...), the named model's own fit
    with those options."""
    from gonio.fitting.pipeline import as_fit_input, fit_measurements

    _one_thread_per_worker()
    inp = as_fit_input(_load(meas))
    name, options = model_spec
    rng = np.random.default_rng(rng_seed)
    if set(fit_kwargs) <= {"loss", "estimate_angles"}:
        return fit_measurements(inp, model=name, options=options, seed=rng_seed, rng=rng,
                                loss=fit_kwargs.get("loss", "chi2"),
                                estimate_angles=fit_kwargs.get("estimate_angles"))[0]
    from gonio.fitting.optimise.mle import fit

    return fit(inp.meas, gm.get(name, **options), rng=rng, **fit_kwargs)


def fit_many(metas, model_spec, first, rng_seed, fit_kwargs):
    """Datasets ``first``, ``first + 1``, ... fitted in turn in one task (same seeds as
    :func:`_fit_one`)."""
    return [_fit_one(m, model_spec, first + k, rng_seed, fit_kwargs) for k, m in enumerate(metas)]


#: points of the first dataset that :func:`_warm_worker` fits: enough for the compiled path
#: (above the numpy path's crossover), small enough to cost a few ms once the kernels exist.
#: Measured (roughconductor, 1e5-point fits, one thread, CPU time): a fresh process's first
#: fit 565 ms, the next ones 160 ms; after a 2000-point warm fit, 194 ms and 160 ms.
WARM_POINTS = 2000

_WARMED: set = set()


def _warm_key(model_spec, fit_kwargs) -> str:
    return repr((model_spec, sorted(fit_kwargs.items())))


def _subset(meas, k):
    """The first ``k`` points of ``meas`` (Measurements; a FitInput's, without its budget),
    for :func:`_warm_worker`."""
    import dataclasses

    from gonio.fitting.pipeline import as_fit_input

    meas = as_fit_input(meas).meas
    if meas.wi.shape[0] <= k:
        return meas
    cut = {f.name: getattr(meas, f.name) for f in dataclasses.fields(meas)}
    for name in ("wi", "wo", "brdf", "brdf_std", "use", "weight", "cluster"):
        if cut.get(name) is not None:
            cut[name] = cut[name][:k]
    return type(meas)(**cut)


def _warm_worker(model_spec, sample, fit_kwargs):
    """Run on every worker (``client.run``) before the fits: one Dr.Jit thread, then one fit
    of ``sample`` (a slice of the first dataset, or its loader: sliced here), which traces and
    compiles the model's kernels in this process; once per worker for a model and fit
    options. Returns whether the worker is warm (False: the sample's fit failed)."""
    _one_thread_per_worker()
    key = _warm_key(model_spec, fit_kwargs)
    if key in _WARMED:
        return True
    try:
        _fit_one(_subset(_load(sample), WARM_POINTS), model_spec, 0, 0, fit_kwargs)
    except Exception:      # a sample the fit refuses: the real fit reports it; nothing warmed
        return False
    _WARMED.add(key)
    return True


#: a task holds at least about this much fitting (seconds, one Dr.Jit thread, estimated by
#: :func:`fit_cost`): Dask costs ~10-50 ms to ship a task and its result
MIN_TASK_S = 0.05


def fit_cost(n_points: int) -> float:
    """A rough estimate of one fit's seconds on one Dr.Jit thread (for :func:`task_chunks`):
    measured (CPU time, GGX, 2026-12-02) roughconductor 6-9 ms at 300-1e3 points, 71 ms at
    1e5; roughplastic 41-44 ms at 300-1e3 points, 330 ms at 1e5."""
    return 0.01 + 1e-6 * float(n_points)


def task_chunks(n_datasets: int, n_threads: int, costs=None, min_cost: float = MIN_TASK_S) -> list:
    """Contiguous ``(start, stop)`` ranges of the datasets, one per Dask task, in the order
    they are submitted (Dask runs independent tasks in that order as threads come free).

    Cut by factoring (Hummel, Schonberg and Flynn, "Factoring: a method for scheduling
    parallel loops", Comm. ACM 35(8), 1992): rounds of ``n_threads`` chunks, each chunk of a
    round holding half the remaining work over ``n_threads``: large tasks first, then ever
    smaller ones, the last a dataset each where the work allows, so that the threads finish
    within about one fit of each other instead of one task (the previous equal cuts, four
    tasks a thread: one thread idle for about half a task at the end, ~5 % of a 16-fit
    batch on 2 workers). Many small fits still travel as a few tasks instead of paying
    Dask's cost of shipping a task and its result (~3 ms over the local cluster's TLS) each.

    ``costs``: each dataset's estimated seconds (:func:`fit_cost`); a chunk then holds
    ``min_cost`` or more (a remainder smaller than that joins the chunk before it).
    Without them (loaders, whose data is not seen here) every dataset counts as one unit
    and a chunk may be a single dataset. ``n_threads <= 0`` (a remote scheduler whose
    workers are not known yet): a task per dataset."""
    if n_datasets <= 0:
        return []
    if n_threads <= 0:
        return [(i, i + 1) for i in range(n_datasets)]
    unit = np.ones(n_datasets) if costs is None else np.asarray(costs, dtype=np.float64)
    if unit.shape != (n_datasets,) or not np.all(np.isfinite(unit)) or np.any(unit < 0):
        raise ValueError(f"costs must be {n_datasets} finite non-negative seconds")
    floor = 0.0 if costs is None else float(min_cost)
    cum = np.concatenate([[0.0], np.cumsum(unit)])
    chunks, a = [], 0
    while a < n_datasets:
        share = max((cum[-1] - cum[a]) / (2 * n_threads), floor)
        for _ in range(n_threads):
            if a >= n_datasets:
                break
            # the first b whose chunk [a, b) holds the share (at least one dataset)
            b = min(max(int(np.searchsorted(cum, cum[a] + share * (1 - 1e-12), side="left")), a + 1), n_datasets)
            if cum[-1] - cum[b] < floor:       # what would be left is too small for a task
                b = n_datasets
            chunks.append((a, b))
            a = b
    return chunks


def model_spec_of(model):
    return (model.name, dict(model.options)) if not isinstance(model, tuple) else model


def fit_serial(datasets, model, *, rng_seed: int = 0, **fit_kwargs) -> list:
    """The same fits as :func:`fit_batch`, in this process (the reference for equality)."""
    return [_fit_one(m, model_spec_of(model), i, rng_seed, fit_kwargs) for i, m in enumerate(datasets)]


def fit_batch(datasets, model, *, scheduler: str | None = None, n_workers: int = 2, rng_seed: int = 0,
              dashboard_address: str | None = None, client=None, **fit_kwargs) -> list:
    """Fit every dataset in ``datasets`` with ``model`` on a Dask cluster.

    Parameters
    ----------
    datasets : sequence of FitInput or Measurements, or of loaders
        A FitInput (:class:`gonio.fitting.pipeline.FitInput`) carries the dataset's budget,
        which the fit needs where the dataset declares apertures; Measurements alone count as
        a FitInput without one. A loader is a function of no arguments that returns either
        (picklable: e.g. ``functools.partial(open_fit_input, path)``); it is called in the
        worker, so the data does not travel through Dask (the workers must see the same files).
        Measurements reach a local cluster's workers through files in a private temporary
        folder (``TMPDIR``; about their size in the page cache while the batch runs), and
        other workers over the cluster.
    model
        A gonio model, or ``(name, options)``: a name whose options leave the microfacet
        distribution open is fitted once per declared distribution and the better kept by
        BIC, as `gonio fit --model NAME` does.
    scheduler : str, optional
        Address of an existing dask.distributed scheduler (``tcp://host:8786``); default: a
        private local cluster of ``n_workers`` single-threaded worker processes (TLS with a
        certificate made for this run), closed afterwards.
    n_workers : int
        1 to :data:`MAX_WORKERS`.
    dashboard_address : str, optional
        Where the local cluster serves its dashboard (e.g. ``127.0.0.1:8787``); default none.
    client : distributed.Client, optional
        An open client to use (and leave open) instead of ``scheduler`` or a local cluster:
        its workers stay warm from one call to the next (:func:`_warm_worker`).
    rng_seed : int
        Every datasets starts draw from ``default_rng(rng_seed)``, as a single fits do.
    fit_kwargs
        Passed to :func:`~gonio.fitting.fit` (loss, fixed, n_starts, ...).

    Returns
    -------
    list of FitResult, in the order of ``datasets``.
    """
    spec = model_spec_of(model)
    if client is not None:
        return _run_batch(client, list(datasets), spec, rng_seed, fit_kwargs)
    from dask.distributed import Client

    cluster = None
    if scheduler is None:
        cluster = local_cluster(n_workers, dashboard_address)
        try:
            client = local_client(cluster, dashboard=dashboard_address is not None)
        except BaseException:
            cluster.close()
            raise
    else:
        address = check_scheduler_address(scheduler)
        try:
            client = Client(address, timeout="20s", set_as_default=False)
        except (TypeError, ValueError) as exc:       # tls:// without certificates in Dask's config
            raise ConnectionError(f"{' '.join(str(exc).split())[:200]}; a tls:// scheduler needs its "
                                  "certificates in Dask's configuration (distributed.comm.tls)") from None
    try:
        return _run_batch(client, list(datasets), spec, rng_seed, fit_kwargs)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _run_batch(client, datasets, spec, rng_seed, fit_kwargs) -> list:
    """The fits on ``client``'s workers (see the module notes): warm each worker not yet
    warm; then, on this process's local worker processes, a task per worker thread that
    claims datasets one at a time (:func:`_run_claimed`; Measurements in memory handed over
    through files), elsewhere a task per contiguous chunk (:func:`_run_chunked`). Results in
    the order of ``datasets``."""
    if not datasets:
        return []
    nthreads = client.nthreads()
    n_threads = sum(nthreads.values())
    first = datasets[0]
    if n_threads > 0:
        _warm_workers(client, set(nthreads), spec, first if callable(first) else _subset(first, WARM_POINTS),
                      fit_kwargs)
    if n_threads > 0 and _local_processes(client):
        from gonio.fitting.batch.handoff import Handoff

        try:
            handoff = Handoff()
        except OSError as exc:
            _handoff_warning(exc)
        else:
            try:
                return _run_claimed(client, datasets, spec, rng_seed, fit_kwargs, handoff, n_threads)
            except _HandoffFailed as exc:
                _handoff_warning(exc.__cause__)
            finally:
                handoff.close()
    return _run_chunked(client, datasets, spec, rng_seed, fit_kwargs, n_threads)


class _HandoffFailed(Exception):
    """The batch's files could not be written (its cause): run it in chunks instead."""


def _fit_claimed(metas, model_spec, rng_seed, fit_kwargs, claims):
    """A task of :func:`_run_claimed`: the datasets of ``metas`` (loaders) this task claims
    first (:func:`gonio.fitting.batch.handoff.claim`), fitted in turn as :func:`_fit_one` would;
    stops when every dataset is claimed or the batch is over (its folder gone, or its
    writer failed). Returns ``[(index, FitResult), ...]``."""
    from gonio.fitting.batch.handoff import BatchOver, claim

    out = []
    for i, meas in enumerate(metas):
        mine = claim(claims, i)
        if mine is None:
            break
        if mine:
            try:
                out.append((i, _fit_one(meas, model_spec, i, rng_seed, fit_kwargs)))
            except BatchOver:
                break
    return out


def _run_claimed(client, datasets, spec, rng_seed, fit_kwargs, handoff, n_threads) -> list:
    """Self-scheduling on local worker processes: one task per worker thread, each taking
    the next unclaimed dataset until none is left (a claim is a file created with
    ``O_EXCL`` in the batch's private folder, ~10 us), so the threads finish within one
    fit of each other whatever the fits' lengths, and Dask ships two tasks and two results
    instead of a task per chunk. Measured (2026-12-03, 2 cores, 2 workers, eight calls
    each): 16 roughconductor fits of 1e5 points 0.499-0.506 s against 0.508-0.513 s in
    factoring's 8 tasks; 64 of 1e3 points 0.214-0.218 s against 0.223-0.227 s.

    Measurements in memory are promised to the tasks (:meth:`Handoff.promise`) and written
    once the tasks are on their way (:meth:`Handoff.write_pending`), in claiming order, so
    the workers start on the first while the later ones are written; a write that fails
    (a full disk) raises :class:`_HandoffFailed` after cancelling the tasks. A dataset
    whose task was lost with its worker (Dask runs the task again elsewhere, and that run
    finds it claimed) is fitted again, alone, afterwards."""
    loaders = [m if callable(m) else handoff.promise(m) for m in datasets]
    k = n_threads
    futures = client.map(_fit_claimed, [loaders] * k, [spec] * k, [rng_seed] * k, [fit_kwargs] * k,
                         [handoff.claims] * k, pure=False)
    try:
        handoff.write_pending()
    except OSError as exc:
        client.cancel(futures)
        raise _HandoffFailed() from exc
    except BaseException:
        client.cancel(futures)
        raise
    got = {}
    try:
        for part in client.gather(futures):
            got.update(part)
    except BaseException:
        client.cancel(futures)
        raise
    missing = [i for i in range(len(loaders)) if i not in got]
    if missing:
        m = len(missing)
        redo = client.map(fit_many, [[loaders[i]] for i in missing], [spec] * m, missing, [rng_seed] * m,
                          [fit_kwargs] * m, pure=False)
        try:
            for i, part in zip(missing, client.gather(redo)):
                got[i] = part[0]
        except BaseException:
            client.cancel(redo)
            raise
    return [got[i] for i in range(len(loaders))]


def _run_chunked(client, datasets, spec, rng_seed, fit_kwargs, n_threads) -> list:
    """A task per contiguous chunk (:func:`task_chunks`), all submitted in one message
    (``client.map``: a loop of ``client.submit`` sends the first at once and the rest ~10 ms
    later, Dask's client batching; the first task then started 12-15 ms after the call,
    against 4-5 ms); Measurements scattered, one object per task; results in order."""
    loaders = all(callable(m) for m in datasets)
    chunks = task_chunks(len(datasets), n_threads,
                         costs=None if any(callable(m) for m in datasets) else
                         [fit_cost(_points(m)) for m in datasets])
    if loaders:      # small: in the graph
        parts = [datasets[a:b] for a, b in chunks]
    else:            # hash=False: no token computed over every array (distinct objects anyway)
        parts = client.scatter([datasets[a:b] for a, b in chunks], hash=False)
    k = len(chunks)
    futures = client.map(fit_many, parts, [spec] * k, [a for a, _ in chunks], [rng_seed] * k, [fit_kwargs] * k,
                         pure=False)
    try:
        return [res for part in client.gather(futures) for res in part]
    finally:
        client.cancel(futures + ([] if loaders else list(parts)))


def _local_processes(client) -> bool:
    """Whether ``client``'s workers are processes of this machine started by this process:
    its cluster a ``LocalCluster`` with processes (they see this process's temporary folder,
    as this user)."""
    try:
        from distributed import LocalCluster
    except ImportError:
        return False
    cluster = getattr(client, "cluster", None)
    return isinstance(cluster, LocalCluster) and bool(getattr(cluster, "processes", False))


def _handoff_warning(exc) -> None:
    import warnings

    warnings.warn(f"fit_batch: could not write the batch's files for the local workers ({exc}); running it "
                  "in chunks, datasets in memory sent over the cluster (slower: free space in the temporary "
                  "folder, or set TMPDIR)", RuntimeWarning, stacklevel=4)


#: (client id, worker address, model and fit options) that :func:`_warm_worker` has run for
_WARM_SEEN: set = set()


def _warm_workers(client, addresses, spec, sample, fit_kwargs) -> None:
    """:func:`_warm_worker` on the workers of ``addresses`` this process has not warmed for
    this model and options through this client (a round trip to every worker, ~2 ms, saved on
    a warm client's later calls; a worker that restarts has a new address and is warmed
    again)."""
    key = _warm_key(spec, fit_kwargs)
    todo = sorted(a for a in addresses if (client.id, a, key) not in _WARM_SEEN)
    if not todo:
        return
    if len(_WARM_SEEN) > 4096:     # many clients come and gone in one process: forget them
        _WARM_SEEN.clear()
    warm = client.run(_warm_worker, spec, sample, fit_kwargs, workers=todo)
    _WARM_SEEN.update((client.id, a, key) for a, ok in warm.items() if ok)
