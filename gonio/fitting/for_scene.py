"""``gonio fit DATA --scene SCENE``'s use case: model only what a scene needs (issue 16).

Every candidate is fitted to the data (as ``--model auto`` or the named model's options do),
then refitted to the pixels the scene shows of the measured material
(:func:`gonio.fitting.selection.by_scene.fit_to_scene`), rendered in the scene beside the
measured BSDF with matched seeds, and the simplest candidate whose mean CIEDE2000 is below the
threshold is chosen (:func:`gonio.fitting.selection.by_scene.rank_in_scene`); the Mitsuba part
runs in a child process under a deadline. :func:`fit_for_scene` returns the fit document: the
chosen candidate's fit to the data with a ``scene`` section (every candidate's scene fit,
rendered difference, noise floor and Mitsuba cost, the speed-versus-error front).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gonio.core.deadline import call_with_deadline
from gonio.core.errors import GonioError
from gonio.fitting.formats.fitfile import fit_document
from gonio.fitting.likelihood.loss import default_loss
from gonio.fitting.pipeline import parse_options, resolve_candidates
from gonio.fitting.selection.by_data import select
from gonio.fitting.selection.by_scene import PRESETS, SAMPLE_ID, fit_to_scene, rank_in_scene
from gonio.fitting.selection.scene_file import checked_scene

__all__ = ["check_scene_options", "fit_for_scene", "RENDERABLE", "TIME_LIMIT_S", "option_text"]

RENDERABLE = (".bsdf", ".binary")
#: seconds the scene's renders and pixel fits may take together (the defaults take ~30 s)
TIME_LIMIT_S = 1800.0


def check_scene_options(scene, dataset: Path, size: int, spp: int, k: int, threshold: float,
                        time_limit: float = TIME_LIMIT_S) -> None:
    """Everything about ``--scene`` that can be checked before any work: one line each."""
    if Path(dataset).suffix.lower() not in RENDERABLE:
        raise GonioError(f"--scene compares renders of the measured material: give an RGL .bsdf or a MERL .binary "
                         f"file (Mitsuba renders those), not {Path(dataset).name}")
    if str(scene) not in PRESETS:
        p = Path(scene)
        if p.suffix.lower() != ".xml" or not p.is_file():
            raise GonioError(f"--scene {str(scene)[:80]!r}: choose one of {', '.join(PRESETS)} or give a Mitsuba "
                             "scene file (.xml) whose sample material is <bsdf ... id=\"sample\">")
        _check_scene_file(p)
    for name, value, lo, hi in (("--scene-size", size, 8, 512), ("--scene-spp", spp, 1, 1 << 16),
                                ("--scene-light-samples", k, 1, 4096)):
        if not lo <= int(value) <= hi:
            raise GonioError(f"{name} {value}: give an integer from {lo} to {hi}")
    if not (math.isfinite(time_limit) and 1 <= time_limit <= 7 * 86400):
        raise GonioError(f"--scene-time-limit {time_limit}: give seconds from 1 to {7 * 86400}")
    if not (math.isfinite(threshold) and threshold > 0):
        raise GonioError(f"--threshold {threshold}: give a positive CIEDE2000 difference (default 1)")


def _check_scene_file(path: Path) -> None:
    root = checked_scene(path)
    n = sum(1 for e in root.iter("bsdf") if e.get("id") == SAMPLE_ID)
    if n != 1:
        raise GonioError(f"--scene {path}: a Mitsuba <scene> with exactly one material <bsdf ... id=\"{SAMPLE_ID}\"> "
                         f"(the sample's) is needed; found {n}")


def _fit_candidates(meas, model, options, seed, loss):
    """The data fits of every candidate: (FitResults, ranking rows)."""
    options = parse_options(options)
    loss = loss or default_loss(meas)
    rng = np.random.default_rng(seed)
    candidates = resolve_candidates(model, options)
    try:
        _, ranking = select(meas, rng=rng, loss=loss, candidates=candidates)
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    return ranking


def _scene_work(data_fits, dataset, scene, size, spp, k, seed, threshold):
    """The Mitsuba part of ``--scene`` (run in a child with a deadline): scene fits and ranking."""
    scene_fits = fit_to_scene(data_fits, dataset, scene, size=size, k=k, rng=np.random.default_rng(seed))
    return scene_fits, rank_in_scene(scene_fits, dataset, scene, size=size, spp=spp, seed=seed, threshold=threshold)


def fit_for_scene(meas, dataset: Path, *, scene, model, options, seed, loss, size=32, spp=256, k=64,
                  threshold=1.0, time_limit=TIME_LIMIT_S) -> tuple[dict, list]:
    """The fit document of the simplest candidate that renders ``scene`` within ``threshold``
    of the measured material, and the data's ranking (GonioError when none does)."""
    check_scene_options(scene, dataset, size, spp, k, threshold, time_limit)
    ranking = _fit_candidates(meas, model, options, seed, loss)
    data_fits = [r.result for r in ranking]
    try:
        scene_fits, ranked = call_with_deadline(
            _scene_work, (data_fits, dataset, scene, size, spp, k, seed, threshold), seconds=time_limit,
            what=f"rendering scene {scene}", hint="give a smaller --scene-size or --scene-spp, a simpler scene, or a "
                                                 "larger --scene-time-limit")
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    rows = ranked["rows"]
    for row, sf in zip(rows, scene_fits):
        row["params"] = _jsonable(sf.params)
        row["scene_fit_rms"] = sf.rms_rel
        row["on_front"] = any(f is row for f in ranked["front"])
    chosen = ranked["chosen"]
    if chosen is None:
        best = min(rows, key=lambda r: r["delta_e"])
        raise GonioError(f"scene {scene}: no candidate renders within CIEDE2000 {threshold:g} of the measured "
                         f"material (best {best['model']} at {best['delta_e']:.2f}); try another --model, or a larger "
                         "--threshold if that difference is acceptable")
    i = rows.index(chosen)
    doc = fit_document(data_fits[i], meas, seed=seed, ranking=ranking, dataset_path=dataset)
    doc["scene"] = {"scene": str(scene), "threshold": threshold, "size": size, "spp": spp, "light_samples": k,
                    "seed": seed, "rows": rows, "front": [r["model"] + option_text(r) for r in ranked["front"]],
                    "chosen": chosen["model"] + option_text(chosen),
                    "mitsuba": scene_fits[i].model.to_mitsuba(scene_fits[i].params),
                    "note": "the fit file's parameters are the chosen model's fit to the data; 'mitsuba' here is "
                            "its fit to the scene's pixels (what the comparison rendered)"}
    return doc, ranking


def option_text(row) -> str:
    """`` (ggx)`` for a row whose options name a distribution, else ``""``."""
    d = row["options"].get("distribution")
    return f" ({d})" if d else ""


def _jsonable(params: dict) -> dict:
    return {k: (np.asarray(v).tolist() if np.ndim(v) else float(v)) for k, v in params.items()}
