"""``gonio perf real DIR...``: gonio's ``--model auto`` on measured materials against a plain peer.

Per material (an RGL-EPFL ``.bsdf`` or a MERL ``.binary``), in the same run: **gonio**,
``--model auto`` as the command line runs it (:func:`gonio.fitting.selection.auto.auto_fit`;
the chosen fit's time and the whole choice's), and the **peer**, what a scipy user would write:
``scipy.optimize.least_squares`` on the unweighted log residuals ln(1 + f_model cos) - ln(1 +
f_meas cos) with ``model.eval`` of Mitsuba's roughplastic (:data:`PEER_FAMILY`), from its
declared defaults and 7 uniform starts (8, seeded), the best kept. Metrics on one dense grid shared by both
(:func:`dense_grid`: theta_i, theta_o <= 80 deg, equal solid-angle cells, the file's f_r at
each): ``ngan`` (Ngan, Durand & Matusik 2005, sec. 4), ``log`` (Loew et al. 2012, eq. 11),
``dE00`` (mean CIEDE2000 of the preview renders, :data:`RENDER_SIZE` pixels square at
:data:`RENDER_SPP` samples per pixel, with the matched-seed noise floor), wall and CPU seconds
and their ratios peer / gonio. Definitions and references: the comment below.
"""

# gonio: every candidate screened with the real-data default loss on a subsample of the file's
# own solid-angle-weighted samples, chosen by the default scene's pixels and BIC, refined where
# the choice renders above 1 and its family declares a refinement (a matte tabulated fit's
# sheen, with the luminance loss), then the chosen one refitted to every sample with its loss
# (gonio.fitting.selection.auto).
# peer: scipy.optimize.least_squares (trust-region reflective, 2-point finite differences,
# bounds), no weights, from the declared defaults and 7 more starts drawn uniformly in the
# parameter box (8 starts, seeded Generator), the best kept, with gonio's model.eval (the
# compiled kernel from compiled_min_pairs pairs where the family has one, as for every user of
# model.eval; its declared defaults: a data-driven model's instance carries gonio's own start,
# which the peer does not get).
# Metrics (w the cell weights, every pair weighs the same):
# * ngan: the cosine-weighted L2 relative to the measured norm,
#   sqrt(sum w ((f_model - f) cos_i)^2 / sum w (f cos_i)^2);
# * log: sqrt(sum w (ln(1 + f_model cos_i) - ln(1 + f cos_i))^2 / sum w);
# * dE00: the rendered difference, mean CIEDE2000 over the preview sphere's pixels under both
#   preview lightings (gonio.fitting.render.preview.preview: the fitted model and the measured
#   file rendered with the same seeds);
# * time: wall seconds and CPU seconds (time.process_time: every thread of the process, Dr.Jit's
#   pool and BLAS's included; gonio's fit holds BLAS to one thread, the peer's scipy does not),
#   and their ratios peer / gonio (same run, same machine). Wall time on the shared machine
#   moves with its load; CPU time much less.
#
# References
# Ngan, A., Durand, F., Matusik, W. (2005). Experimental analysis of BRDF models. EGSR.
# Loew, J., Kronander, J., Ynnerman, A., Unger, J. (2012). BRDF models for accurate and
# efficient rendering of glossy surfaces. ACM TOG 31(1).

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
import scipy.optimize

from gonio.core.atomic import atomic_open
from gonio.core.geometry import equal_solid_angle_pairs
# the dE00 limit is 1 below MATTE_BELOW_GU (60 deg gloss, ASTM D523), else 2
from gonio.models.physics.gloss import GLOSS_APERTURE_DEG, GLOSS_STANDARD_N, MATTE_BELOW_GU, specular_gloss  # noqa: F401

from gonio.fitting.likelihood.loss import REAL_DEFAULT_LOSS
from gonio.fitting.realdata import merl_samples, rgl_samples
from gonio.fitting.selection.by_data import select
from gonio.fitting.optimise.space import ParameterSpace
from gonio.fitting.formats import RGLBRDF, read_merl

__all__ = ["dense_grid", "metrics", "peer_fit", "run_real", "specular_gloss", "warm_up", "PEER_STARTS", "WARM_UP_POINTS"]

PEER_STARTS = 8
#: the plain peer's family (issue 35: Mitsuba's roughplastic); "same" fits the family gonio chose
PEER_FAMILY = "roughplastic"
#: samples of the first file both sides run on once before the timed rows (:func:`warm_up`)
WARM_UP_POINTS = 400
#: the rendered comparison: preview sphere size (pixels) and samples per pixel (the issue's 256)
RENDER_SIZE, RENDER_SPP = 64, 256
#: gonio's fit rendered again at 16 times the samples: what the 256-spp figure's Monte Carlo bias
#: is (a mean CIEDE2000 of two noisy images is biased upwards; matched seeds remove only the
#: noise both renders share: leaf_maple 1.04 at 256 spp, 0.97 at 4096, docs/performance.md)
CONVERGED_SPP = 4096
#: dense grid: theta_i and theta_o rings equal in solid angle (cos theta uniform), phi cells
N_THETA_I, N_THETA_O, N_PHI_O = 12, 24, 48


def dense_grid(theta_max_deg=80.0, n_theta_i=N_THETA_I, n_theta_o=N_THETA_O, n_phi_o=N_PHI_O):
    """The issue's dense grid: (wi, wo) on equal-solid-angle cells of both hemispheres below
    ``theta_max_deg`` (:func:`~gonio.core.geometry.equal_solid_angle_pairs`), every pair of
    the same solid-angle weight."""
    return equal_solid_angle_pairs(theta_max_deg, n_theta_i, n_theta_o, n_phi_o)


def measured_on_grid(path, wi, wo):
    """f_r of the measured file at (wi, wo), (N, 3)."""
    if str(path).lower().endswith(".binary"):
        f = read_merl(path).eval(wi, wo)
        return np.where(np.isfinite(f), f, 0.0)
    return RGLBRDF(path).eval(wi, wo)



def metrics(f_model, f_meas, wi) -> dict:
    """Ngan's relative cosine-weighted L2 and Loew's log error on an equal-weight grid."""
    cos_i = np.clip(wi[:, 2:3], 0.0, 1.0)
    f_model = np.asarray(f_model, dtype=np.float64)
    if not np.all(np.isfinite(f_model)):
        raise FloatingPointError("the fitted model is not finite on the evaluation grid")
    ngan = float(np.sqrt(np.sum(((f_model - f_meas) * cos_i) ** 2) / np.sum((f_meas * cos_i) ** 2)))
    lm = np.log1p(np.maximum(f_model * cos_i, -0.999))
    ld = np.log1p(np.maximum(f_meas * cos_i, -0.999))
    return {"ngan": ngan, "log": float(np.sqrt(np.mean((lm - ld) ** 2)))}


def _log_residuals(model, space, meas, x):
    cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
    f = np.asarray(model.eval(meas.wi, meas.wo, space.to_params(x)), dtype=np.float64)
    r = np.log1p(np.maximum(f * cos_i, -0.999)) - np.log1p(np.maximum(meas.brdf * cos_i, -0.999))
    return np.where(np.isfinite(r), r, 1e3)[meas.use]


def _mitsuba_log_residuals(model, space, meas, x):
    """As :func:`_log_residuals`, f_r cos from Mitsuba's own BSDF (``model.to_mitsuba``, loaded
    and evaluated by Mitsuba at every call, as a script without gonio would)."""
    from gonio.models.mitsuba import eval_cos

    fc = eval_cos(model.to_mitsuba(space.to_params(x)), meas.wi, meas.wo)
    cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
    r = np.log1p(np.maximum(fc, -0.999)) - np.log1p(np.maximum(meas.brdf * cos_i, -0.999))
    return np.where(np.isfinite(r), r, 1e3)[meas.use]


#: how the peer evaluates its model: ``mitsuba``, Mitsuba's own BSDF (issue 35's plain fit as
#: written); ``gonio``, gonio's model.eval (the compiled kernel: a stronger peer, ~10x faster)
PEER_EVALS = ("mitsuba", "gonio")
#: the relative finite-difference step of the peer on Mitsuba's float32 evaluation
MITSUBA_DIFF_STEP = 1e-3


def peer_fit(meas, model, rng, n_starts=PEER_STARTS, evaluate="gonio"):
    """The plain peer: scipy least_squares on the unweighted log residuals, the model evaluated
    by ``evaluate`` (:data:`PEER_EVALS`), from the defaults and ``n_starts - 1`` uniform draws
    of the box. (space, x, wall seconds, CPU seconds)."""
    if evaluate not in PEER_EVALS:
        raise ValueError(f"peer evaluation {evaluate!r}: choose one of {', '.join(PEER_EVALS)}")
    residuals = _mitsuba_log_residuals if evaluate == "mitsuba" else _log_residuals
    # Mitsuba evaluates in float32 (its pip variants): scipy's default relative step (1.5e-8)
    # moves nothing there, so the differences need a step above its rounding (sqrt(6e-8) ~ 2.4e-4)
    diff_step = MITSUBA_DIFF_STEP if evaluate == "mitsuba" else None
    space = ParameterSpace(model, meas.n_channels)
    starts = [space.default()] + [space.from_unit(rng.uniform(0.02, 0.98, space.size)) for _ in range(n_starts - 1)]
    t0, c0 = time.perf_counter(), time.process_time()
    best = None
    for x0 in starts:
        res = scipy.optimize.least_squares(lambda x: residuals(model, space, meas, x), x0,
                                           bounds=(space.lower, space.upper), diff_step=diff_step)
        if best is None or res.cost < best.cost:
            best = res
    return space, best.x, time.perf_counter() - t0, time.process_time() - c0


def _alone_time(meas, model, *, seed, loss):
    """Wall seconds of the chosen family fitted on its own, as ``gonio fit --model NAME
    [--option ...]`` fits it (its own starts, covariance and energy polish): the cost the
    issue's "choosing costs at most 10x the chosen fit" compares with."""
    from gonio.fitting.pipeline import fit_measurements

    t0 = time.perf_counter()
    fit_measurements(meas, model=model.name, options=dict(model.options) or None, seed=seed, loss=loss)
    return time.perf_counter() - t0


def rendered_delta_e(model, params, path, seed=0, size=RENDER_SIZE, spp=RENDER_SPP, noise_floor=True):
    """(mean CIEDE2000 over both lightings, its matched-seed noise floor) of the model
    against the measured file, rendered with the same seeds (images in a temporary folder);
    the floor is NaN with ``noise_floor=False`` (half the renders)."""
    import tempfile

    from gonio.fitting.render.preview import preview

    with tempfile.TemporaryDirectory() as tmp:
        out = preview(model, params, tmp, measured=Path(path), size=size, spp=spp, seed=seed, noise_floor=noise_floor)
    floor = float(np.mean([v["noise_mean"] for v in out["delta_e"].values()])) if noise_floor else float("nan")
    return float(out["delta_e_mean"]), floor


def rendered_delta_e_on_grid(model, params, path, seed=0, size=RENDER_SIZE, spp=RENDER_SPP, wi=None, wo=None):
    """The model written on the RGL file's own grid (:func:`~gonio.fitting.formats.rgl_grid.fit_on_rgl_grid`)
    and rendered through Mitsuba's ``measured`` plugin beside the file, with the same seeds:
    both renders draw the same directions, so the figure carries the values' difference and
    not the two plugins' sampling noise. Returns ``{"de00", "floor", "grid_l2"}``: the mean
    CIEDE2000, its matched-seed noise floor, and the written file's Ngan relative L2 error
    against the model itself at (``wi``, ``wo``) (what the grid's interpolation changes; NaN
    without them)."""
    import tempfile

    from gonio.fitting.formats.rgl_grid import fit_on_rgl_grid, grid_error
    from gonio.fitting.render.preview import preview

    with tempfile.TemporaryDirectory() as tmp:
        table = Path(tmp) / "fit_on_grid.bsdf"
        fit_on_rgl_grid(model, params, path, table, description=f"gonio perf real: {model.name} on {Path(path).name}'s grid")
        error = grid_error(model, params, table, wi, wo) if wi is not None else float("nan")
        out = preview(_TableModel(table), {}, Path(tmp) / "render", measured=Path(path), size=size, spp=spp, seed=seed)
    floor = float(np.mean([v["noise_mean"] for v in out["delta_e"].values()]))
    return {"de00": float(out["delta_e_mean"]), "floor": floor, "grid_l2": error}


class _TableModel:
    """What :func:`preview` renders: an RGL file through Mitsuba's ``measured`` plugin."""

    def __init__(self, path):
        self.path = str(path)

    def to_mitsuba(self, params):
        return {"type": "measured", "filename": self.path}


def _samples(path: Path, seed, open_data):
    """The material's samples as gonio fits them: ``open_data(path)`` where given, else the
    RGL file's, or 5000 seeded samples of a MERL ``.binary``."""
    if open_data is not None:
        return open_data(path)
    if path.suffix.lower() == ".binary":
        return merl_samples(path, n=5000, rng=np.random.default_rng(seed))
    return rgl_samples(path)


def compare(path, *, seed=0, loss=None, open_data=None, render=True, peer=PEER_FAMILY, peer_eval="gonio"):
    """One material: a dict of gonio's chosen fit and the peer's, metrics on the dense grid."""
    path = Path(path)
    loss = loss or REAL_DEFAULT_LOSS
    meas = _samples(path, seed, open_data)
    wi, wo = dense_grid()
    f_meas = measured_on_grid(path, wi, wo)
    if render:      # the one-time imports outside the timing, as the peer's scipy and Mitsuba are
        import colour  # noqa: F401  (delta_e_2000's colour science: 1.7 s, once a process)

        import gonio.fitting.selection.auto  # noqa: F401
        import gonio.fitting.selection.by_pixels  # noqa: F401
    t0, c0 = time.perf_counter(), time.process_time()
    if render:      # as `gonio fit --model auto` on a measured file: screened, chosen by pixels, refitted
        from gonio.fitting.selection.auto import auto_fit

        best, ranking, _ = auto_fit(meas, str(path), seed=seed, loss=loss, rng=np.random.default_rng(seed))
    else:
        best, ranking = select(meas, rng=np.random.default_rng(seed), loss=loss)
    t_select, c_select = time.perf_counter() - t0, time.process_time() - c0
    chosen = next(r for r in ranking if r.chosen)
    model = best.model
    g = metrics(model.eval(wi, wo, best.params), f_meas, wi)
    import gonio.models as gm

    # the peer: Mitsuba's roughplastic (its declared defaults, not gonio's start) unless a
    # family is named ("same": the family gonio chose)
    peer_model = gm.get(model.name, **model.options) if peer == "same" else gm.get(peer)
    space, x_peer, t_peer, c_peer = peer_fit(meas, peer_model, np.random.default_rng([seed, 1]), evaluate=peer_eval)
    p = metrics(peer_model.eval(wi, wo, space.to_params(x_peer)), f_meas, wi)
    t_alone = _alone_time(meas, model, seed=seed, loss=best.loss)       # the loss the chosen fit was fitted with
    label = model.name + (f"-{model.options['distribution']}" if model.options.get("distribution") else "") + (
        "-body" if model.options.get("body") == "table" else "") + ("-ring" if model.options.get("ring") == "table" else "") + (
        "-sheen" if model.options.get("sheen") == "ggx" else "")
    cpu = best.cpu_s if best.cpu_s is not None else float("nan")
    de_g = de_p = floor = de_conv = float("nan")
    grid = {"de00": float("nan"), "floor": float("nan"), "grid_l2": float("nan")}
    if render:
        de_g, floor = rendered_delta_e(model, best.params, path, seed)
        de_conv, _ = rendered_delta_e(model, best.params, path, seed, spp=CONVERGED_SPP, noise_floor=False)
        de_p, _ = rendered_delta_e(peer_model, space.to_params(x_peer), path, seed)
        if path.suffix.lower() == ".bsdf":
            try:
                grid = rendered_delta_e_on_grid(model, best.params, path, seed, wi=wi, wo=wo)
            except ValueError as exc:       # a grid gonio cannot write on: the row keeps NaN there
                print(f"{path.name}: the fit on the file's own grid: {' '.join(str(exc).split())[:200]}", flush=True)
    gloss = specular_gloss(lambda a, b: measured_on_grid(path, a, b))
    return {"gonio_de00": de_g, "gonio_de00_converged": de_conv, "gonio_de00_grid": grid["de00"], "grid_noise": grid["floor"],
            "grid_l2": grid["grid_l2"], "peer_de00": de_p, "de00_noise": floor, "gloss_60": gloss,
            "de00_limit": 1.0 if gloss < MATTE_BELOW_GU else 2.0,
            "material": path.stem, "model": label, "peer_model": peer_model.name, "peer_eval": peer_eval, "loss": best.loss, "samples": meas.n_points, "grid_pairs": len(wi),
            "gonio_ngan": g["ngan"], "gonio_log": g["log"], "gonio_time_s": best.time_s,
            "gonio_cpu_s": cpu, "gonio_select_s": t_select, "gonio_select_cpu_s": c_select,
            "gonio_chi2_dof": best.chi2_dof,
            "peer_ngan": p["ngan"], "peer_log": p["log"], "peer_time_s": t_peer, "peer_cpu_s": c_peer,
            "alone_s": t_alone, "choice_per_fit": t_select / max(t_alone, 1e-9),
            "speedup": t_peer / max(t_select, 1e-9), "speedup_cpu": c_peer / max(c_select, 1e-9),
            "candidates": len(ranking),
            "chosen_k": chosen.k}


COLUMNS = (("material", "<26", "s"), ("model", "<28", "s"), ("loss", "<10", "s"), ("gonio_ngan", ">9", ".3f"),
           ("peer_ngan", ">9", ".3f"), ("gonio_log", ">9", ".4f"), ("peer_log", ">9", ".4f"),
           ("gonio_time_s", ">9", ".2f"), ("gonio_select_s", ">9", ".1f"), ("alone_s", ">9", ".1f"),
           ("choice_per_fit", ">8", ".1f"), ("peer_time_s", ">9", ".1f"), ("speedup", ">8", ".2f"),
           ("gonio_select_cpu_s", ">9", ".1f"), ("peer_cpu_s", ">9", ".1f"), ("speedup_cpu", ">8", ".2f"),
           ("gonio_de00", ">8", ".2f"), ("gonio_de00_converged", ">8", ".2f"), ("gonio_de00_grid", ">8", ".2f"),
           ("grid_noise", ">7", ".2f"), ("grid_l2", ">8", ".3f"), ("peer_de00", ">8", ".2f"),
           ("de00_noise", ">7", ".2f"), ("gloss_60", ">7", ".1f"), ("de00_limit", ">6", ".0f"))
HEADS = {"gonio_ngan": "Ngan g", "peer_ngan": "Ngan p", "gonio_log": "log g", "peer_log": "log p",
         "gonio_time_s": "t g s", "peer_time_s": "t p s", "speedup": "p/auto", "gonio_select_cpu_s": "cpu auto",
         "peer_cpu_s": "cpu p s", "speedup_cpu": "cpu p/a", "gonio_select_s": "auto s", "alone_s": "alone s",
         "choice_per_fit": "auto/al",
         "gonio_de00": "dE g", "gonio_de00_converged": "dE g 4k", "gonio_de00_grid": "dE grid", "grid_noise": "gfloor", "grid_l2": "grid L2", "peer_de00": "dE p", "de00_noise": "floor", "gloss_60": "G60", "de00_limit": "lim"}


def print_table(rows, legend=True, head=True):
    line = "".join(f"{HEADS.get(k, k):{fmt}}" for k, fmt, _ in COLUMNS)
    if head:
        print(line)
        print("-" * len(line))
    for r in rows:
        print("".join(f"{r[k]:{fmt}{spec if spec != 's' else ''}}" for k, fmt, spec in COLUMNS), flush=True)
    if not legend:
        return
    print("g: gonio's chosen fit (--model auto: every candidate screened on a subsample; among the proper ones "
          "whose product-shot pixels are within CIEDE2000 0.5 of the closest, BIC chooses; tabulated is tried where "
          "none is within 1, and refined (a matte tabulated fit's sheen, luminance loss) where that renders "
          "closer; the chosen one refitted to all samples); p: scipy least_squares, unweighted "
          "log loss, "
          f"{PEER_STARTS} starts, Mitsuba's "
          f"{', '.join(sorted({str(r.get('peer_model', PEER_FAMILY)) for r in rows})) or PEER_FAMILY} evaluated by "
          f"{' and '.join(sorted({_EVAL_TEXT[r.get('peer_eval', 'gonio')] for r in rows}))}; "
          "t g: the chosen fit's refit (wall), auto: the whole selection (wall), alone: the chosen family fitted "
          "on its own as `gonio fit --model NAME` fits it, auto/al: their ratio, p/auto: the peer's time over the "
          "whole selection's (above 1: gonio chose faster than the peer fitted), cpu: CPU time (every thread of "
          "the process); metrics on one dense equal-solid-angle grid (theta <= 80 deg); "
          f"dE: mean CIEDE2000 of the preview sphere against the measured file ({RENDER_SIZE} px, {RENDER_SPP} spp, "
          "env and area lights, matched seeds), floor: its Monte Carlo noise, "
          f"dE g 4k: gonio's at {CONVERGED_SPP} spp (what the {RENDER_SPP}-spp figure's noise adds to it); dE grid: gonio's fit "
          f"written on the RGL file's own grid and rendered through Mitsuba's measured plugin as the file is ({RENDER_SPP} spp: both "
          "renders draw the same directions), gfloor: its noise floor, grid L2: that file's Ngan relative L2 error against the fit itself "
          "(where it is large, the grid does not hold the fit and dE grid is not the fit's); G60: the file's ASTM D523 60 deg "
          f"specular gloss (GU), lim: the issue's dE limit (1 where G60 < {MATTE_BELOW_GU:g}: matte, else 2)")


_EVAL_TEXT = {"gonio": "gonio's model.eval (its compiled kernel)", "mitsuba": "Mitsuba itself (load_dict and eval)"}


def warm_up(path, *, seed=0, loss=None, open_data=None, peer=PEER_FAMILY, peer_eval="gonio", n=WARM_UP_POINTS):
    """Both sides once, untimed in the rows, on ``n`` samples of ``path``: the process's
    one-time costs (imports, Dr.Jit's tracing and compiling of every kernel either side uses)
    paid before the first material, as in a batch they are paid once for all. Returns the wall
    seconds (gonio, peer), which :func:`run_real` prints."""
    from gonio.fitting.selection.auto import auto_fit, subsample

    import gonio.models as gm

    path = Path(path)
    loss = loss or REAL_DEFAULT_LOSS
    meas = subsample(_samples(path, seed, open_data), n, np.random.default_rng([int(seed), 354]))
    t0 = time.perf_counter()
    auto_fit(meas, str(path), seed=seed, loss=loss, rng=np.random.default_rng(seed))
    t1 = time.perf_counter()
    peer_fit(meas, gm.get(PEER_FAMILY if peer == "same" else peer), np.random.default_rng([seed, 1]), n_starts=1,
             evaluate=peer_eval)
    return t1 - t0, time.perf_counter() - t1


def run_real(files, out=None, seed=0, loss=None, open_data=None, peer=PEER_FAMILY, peer_eval="gonio",
             warm=True) -> list[dict]:
    """Every material of ``files``; print the table; with ``out`` write it as CSV there.
    ``peer_eval``: how the peer evaluates its model (:data:`PEER_EVALS`); ``warm``: both sides
    first run once on the first file (:func:`warm_up`), so that every row is a batch's
    steady state; its seconds are printed, not hidden."""
    rows = []
    if warm and files:
        wg, wp = warm_up(files[0], seed=seed, loss=loss, open_data=open_data, peer=peer, peer_eval=peer_eval)
        print(f"warm-up on {WARM_UP_POINTS} samples of {Path(files[0]).stem} (one-time costs, not in the rows): "
              f"gonio {wg:.1f} s, peer {wp:.1f} s", flush=True)
    for f in files:
        rows.append(compare(f, seed=seed, loss=loss, open_data=open_data, peer=peer, peer_eval=peer_eval))
        print_table(rows[-1:], legend=False, head=len(rows) == 1)
    print()
    print_table(rows)
    if out is not None:
        out = Path(out)
        path = out if out.suffix.lower() == ".csv" else out / "fit_bench_real.csv"
        path.parent.mkdir(parents=True, exist_ok=True)

        with atomic_open(path, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"wrote {path}")
    return rows
