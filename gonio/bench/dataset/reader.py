"""Any dataset a user gives, opened as the fitter sees it: a gonio ``dataset.nc``, a MERL
``.binary`` or an RGL ``.bsdf`` file as Measurements, and a dataset.nc's uncertainty budget;
:func:`open_fit_input` both, as every fit path takes them (`gonio fit`, each batch worker); one line (GonioError) for what is missing, a folder, damaged or too large. A sequential plan's ``design_weight`` becomes the Measurements' weight."""

from __future__ import annotations

import contextlib
import gc
import sys
from pathlib import Path

import numpy as np

from gonio.core.errors import GonioError
from gonio.core.hdf5check import check_hdf5
from gonio.core.preflight import check_input_file

__all__ = ["open_dataset", "open_budget", "open_fit_input"]


@contextlib.contextmanager
def _quiet_reader_cleanup():
    """A damaged NetCDF file leaves a half-built h5netcdf File whose ``close`` raises when it is
    collected ("Exception ignored in ... Traceback" on stderr): collect it here, quietly."""
    previous = sys.unraisablehook

    def hook(unraisable):
        module = str(getattr(getattr(unraisable, "object", None), "__module__", "") or "")
        if not module.startswith(("h5netcdf", "h5py")):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        gc.collect()
        sys.unraisablehook = previous


def open_dataset(path: Path, seed: int = 0, colour_space: str = "srgb"):
    """A gonio dataset.nc, a MERL .binary file, an RGL .bsdf file or a Zemax/LightTools tabular
    BSDF (told apart from an RGL file by its content), as Measurements.

    MERL and RGL files carry no uncertainty: each value gets a nominal relative 1-sigma (1 %
    MERL, 2 % RGL; ``attrs["nominal_sigma"]``) and a solid-angle weight. A MERL table is
    subsampled to 5000 of its bins (seeded); an RGL file is sampled on its own measured
    layout (:func:`gonio.fitting.rgl_samples`: every measured theta_i <= 80 deg, 1152 outgoing
    directions each, half by the material's importance sampling so the peak is resolved),
    or at the ``standard`` plan's geometry where only scalar Mitsuba runs.
    """
    from gonio.fitting import load_dataset

    if not path.exists():
        raise GonioError(f"dataset {path} does not exist; run `gonio export SESSION` to write one")
    if path.is_dir():
        hint = f" (e.g. {path / 'dataset.nc'})" if (path / "dataset.nc").exists() else ""
        raise GonioError(f"dataset {path} is a folder; give the dataset file{hint}")
    check_input_file(path, "dataset")           # a regular file: a FIFO would block, /dev/zero never end
    suffix = path.suffix.lower()
    # a damaged file leaves half-built reader objects behind, freed with the exception: all
    # inside the quiet hook, so that their failing close() prints nothing
    with _quiet_reader_cleanup():
        try:
            from gonio.fitting.formats import astm

            if astm.is_astm(path):          # by content: ASTM E1392 text, one channel per wavelength
                return astm.astm_measurements(path)
            if suffix == ".binary":
                from gonio.fitting import merl_samples

                return merl_samples(path, n=5000, rng=np.random.default_rng(seed))
            from gonio.fitting.formats import zemax

            if zemax.is_zemax_bsdf(path):   # by content: Zemax and RGL both write .bsdf
                return zemax.zemax_measurements(path, as_rgb=True)
            if suffix == ".bsdf":
                from gonio.fitting import direction, rgl_samples
                from gonio.fitting.formats import rgl_measurements

                from gonio.bench.plan.plans import load_plan

                try:        # the file's own measured layout, solid-angle weighted
                    return rgl_samples(path)
                except ValueError as exc:
                    if "vectorised Mitsuba variant" not in str(exc):
                        raise
                a = np.radians(load_plan("standard").angles)     # scalar_rgb only: the standard plan
                return rgl_measurements(path, direction(a[:, 0], a[:, 1]), direction(a[:, 2], a[:, 3]))
            check_hdf5(path)            # a damaged file can loop in HDF5 for ever: walked first, in a child
            return _with_design_weight(path, load_dataset(path, colour_space=colour_space))
        except GonioError:
            raise
        except MemoryError:
            message = f"{path} is too large to read on this machine"
        except Exception as exc:            # a damaged file: HDF5 answers KeyError, RuntimeError, ...
            reason = " ".join(str(exc).split())[:300] or type(exc).__name__
            if "filter returned failure" in reason:     # HDF5's Fletcher-32 check of a stored block
                reason = "a stored block fails its checksum: the file is damaged"
            message = (f"cannot read {path} ({reason}); give a dataset.nc written by "
                       "gonio export, a MERL .binary, an RGL .bsdf or a Zemax tabular BSDF file")
    raise GonioError(message)


def _with_design_weight(path: Path, meas):
    """``meas`` with a sequential plan's ``design_weight`` (sr^2, gonio.bench.plan.design_weights) as
    its per-point weight, which the likelihood applies; ValueError where it is not one finite value
    > 0 per point."""
    import xarray as xr

    from gonio.bench.plan.design_weights import VARIABLE

    with xr.open_dataset(path, engine="h5netcdf") as ds:
        if VARIABLE not in ds.variables:
            return meas
        w = np.asarray(ds[VARIABLE].values, float)
    if w.shape != (meas.n_points,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"{VARIABLE} must hold one finite weight > 0 per point; re-export the session")
    meas.weight = w
    return meas


def open_budget(path: Path, meas):
    """The uncertainty budget of a dataset.nc (None for MERL/RGL files: from ``meas.attrs``)."""
    from gonio.fitting import load_budget

    if path.suffix.lower() in (".binary", ".bsdf") or _is_zemax(path) or _is_astm(path):
        return None
    try:
        return load_budget(path, meas)
    except ValueError as exc:
        raise GonioError(" ".join(str(exc).split())) from None


def open_fit_input(path: Path, seed: int = 0, colour_space: str = "srgb"):
    """What a fit of the dataset at ``path`` needs (:class:`gonio.fitting.pipeline.FitInput`):
    :func:`open_dataset`'s Measurements and :func:`open_budget`'s budget. The one way a file
    becomes a fit's input, so that a single fit and a batch worker fit the same thing."""
    from gonio.fitting.pipeline import FitInput

    path = Path(path)
    meas = open_dataset(path, seed, colour_space)
    return FitInput(meas, open_budget(path, meas))


def _is_astm(path: Path) -> bool:
    from gonio.fitting.formats.astm import is_astm

    return is_astm(path)


def _is_zemax(path: Path) -> bool:
    from gonio.fitting.formats.zemax import is_zemax_bsdf

    return is_zemax_bsdf(path)
