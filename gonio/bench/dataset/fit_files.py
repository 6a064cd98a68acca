"""``gonio fit --batch``'s use case: many dataset files fitted with one named model on Dask, a
fit file each.

Every dataset is opened as ``gonio fit`` opens it (`gonio.bench.dataset.reader.open_fit_input`:
Measurements and budget), fitted by the same pipeline in a worker
(`gonio.fitting.batch.dask_batch.fit_batch`), and written as the same fit document; the names
are the datasets' stems (numbered where two collide). Everything a user gives (model, loss,
workers, scheduler, dashboard, the output folder) is checked before any work starts.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Callable

import gonio.models as gm
from gonio.bench.dataset.reader import open_fit_input
from gonio.core.errors import GonioError
from gonio.core.preflight import check_output_dir, writing
from gonio.fitting import (LOSSES, check_dashboard_address, check_scheduler_address, check_workers, default_loss,
                           fit_batch, write_json_atomic)
from gonio.fitting.display import inadequate_text, shared_angles_line
from gonio.fitting.pipeline import check_estimate_angles, fit_document_of, model_error, parse_options

__all__ = ["fit_files", "check_batch_options", "stems_of"]


def check_batch_options(*, model, options, loss, scheduler, workers, dashboard) -> None:
    """Everything about a batch that can be checked before any work: one line each."""
    if model == "auto":
        raise GonioError("--batch needs a named --model (e.g. roughplastic); auto is for single fits")
    if loss is not None and loss not in LOSSES:
        raise GonioError(f"unknown loss {loss!r}: choose one of {', '.join(LOSSES)}")
    try:
        if scheduler is None:
            check_workers(workers)
            if dashboard is not None:
                check_dashboard_address(dashboard)
        else:
            check_scheduler_address(scheduler)
            if dashboard is not None:
                raise ValueError("--dashboard is for the local cluster; an existing scheduler serves its own")
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    try:
        gm.get(model, **parse_options(options))         # a model and options the registry knows
    except (KeyError, ValueError, TypeError) as exc:
        raise model_error(exc, model, auto=False) from None


def stems_of(datasets) -> list[str]:
    """A fit file's name for each dataset: its folder's name for a ``dataset.nc``, else its stem;
    numbered (``0003_name``) where two would collide."""
    stems = [d.parent.name if d.name == "dataset.nc" else d.stem for d in datasets]
    if len(set(stems)) != len(stems):
        stems = [f"{k:04d}_{s}" for k, s in enumerate(stems)]
    return stems


def fit_files(datasets, *, model, options, out: Path, seed, loss, scheduler, workers, dashboard=None,
              say: Callable[[str], None] = print, warn: Callable[[str], None] = print,
              estimate_angles: bool | None = None) -> list[tuple[str, dict]]:
    """Fit ``datasets`` (paths) with ``model`` on Dask and write ``out/STEM.fit.json`` for each;
    ``say`` gets a line per fit and the summary, ``warn`` the fits that miss their data and
    the shared-angle estimates not applied. ``estimate_angles``: as ``gonio fit``'s (None:
    wherever a dataset states the shared angle inputs and the loss is chi2; True: every dataset
    must state them and the loss must be chi2, both checked before any fit; False: never).
    Returns ``[(stem, fit document)]`` in the order of ``datasets``."""
    datasets = [Path(d) for d in datasets]
    check_batch_options(model=model, options=options, loss=loss, scheduler=scheduler, workers=workers,
                        dashboard=dashboard)
    check_output_dir(out, "batch output folder (--out)")
    # each dataset as `gonio fit` opens it: Measurements and budget (one FitInput)
    inputs = [open_fit_input(d, seed) for d in datasets]
    if loss is None:
        defaults = sorted({default_loss(i.meas) for i in inputs})
        if len(defaults) > 1:
            raise GonioError(f"these datasets have different default losses ({', '.join(defaults)}: measured sigma "
                             "or none); give --loss, or fit them in separate batches")
        loss = defaults[0]
    for d, i in zip(datasets, inputs) if estimate_angles is True else ():     # before any fit, as gonio fit's
        check_estimate_angles(i.budget, loss, d)
    extra = {} if estimate_angles is None else {"estimate_angles": estimate_angles}
    stems = stems_of(datasets)
    # a local cluster reads the same files: each worker loads its own datasets (a loader per
    # file, called where it is fitted) instead of receiving them over the cluster's TLS (16
    # datasets of 1e5 points: 1.2 s of CPU to ship against 1.5 s to fit them); an existing
    # scheduler's workers may not see these paths, so they get the data itself
    work = [functools.partial(open_fit_input, d, seed) for d in datasets] if scheduler is None else inputs
    try:
        # (name, the user's options): each worker fits as `gonio fit` does (gonio.fitting.pipeline)
        results = fit_batch(work, (model, parse_options(options)), scheduler=scheduler,
                            n_workers=min(workers, len(inputs)), rng_seed=seed, loss=loss, dashboard_address=dashboard,
                            **extra)
    except (OSError, TimeoutError) as exc:
        if scheduler is None:
            raise GonioError(f"the local Dask cluster failed ({' '.join(str(exc).split())[:200]})") from None
        raise GonioError(f"cannot reach the Dask scheduler {scheduler} ({' '.join(str(exc).split())[:320]}); "
                         "check the address and that it is running") from None
    except ValueError as exc:           # a dataset the fit refuses (raised in a worker)
        raise GonioError(" ".join(str(exc).split())) from None
    except Exception as exc:
        if type(exc).__module__.startswith("distributed"):      # KilledWorker, CommClosedError, ...
            raise GonioError(f"the Dask cluster lost a worker or a connection ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]}); run again, or with fewer --workers") from None
        raise
    out.mkdir(parents=True, exist_ok=True)
    poor, docs = [], []
    for path, inp, result, stem in zip(datasets, inputs, results, stems):
        doc = fit_document_of(result, inp, seed=seed, dataset_path=path)
        with writing(out / f"{stem}.fit.json"):
            write_json_atomic(out / f"{stem}.fit.json", doc)
        docs.append((stem, doc))
        say(f"{stem}: chi2/dof {result.chi2_dof:.3f}, " + ", ".join(
            f"{n}={v:.4g}+-{e:.2g}" for n, v, e in zip(result.space.names, result.x, result.std)))
        g = doc["goodness"]
        if g.get("warning") or g.get("model_adequate") is False:
            poor.append(stem)
            warn(f"  warning: {g.get('warning') or inadequate_text(g)}")
        if (doc.get("shared_angles") or {}).get("applied") is False:     # as `gonio fit` says it
            warn(f"  {stem}: {shared_angles_line(doc)}")
    if poor:
        warn(f"warning: {len(poor)} of {len(results)} fits miss their data by more than its noise: "
             f"{', '.join(poor[:10])}{' ...' if len(poor) > 10 else ''}")
    say(f"wrote {len(results)} fit files to {out}")
    return docs
