"""Model only what a scene needs: the simplest fitted candidate that renders like the measured BSDF.

Every fitted candidate and the measured BSDF are rendered in the scene the material will be
used in, with matched seeds. A scene is a preset (:data:`PRESETS`: ``overcast``,
``product-shot``, ``close-up-sun``; each puts the material on a sphere) or a Mitsuba XML scene
file whose sample material is marked ``<bsdf type="..." id="sample">``. For each candidate:
the mean CIEDE2000 (Sharma et al. 2005) of its render against the measured one over the
pixels that see the material, that comparison's noise floor from a second matched pair of
seeds, and the BSDF's evaluation cost; :func:`front` gives the speed-versus-error front. The
chosen one is the simplest (fewest parameters, then the closest) whose mean difference is
below ``threshold``; ValueError when a simpler candidate can be told neither good nor bad
(more samples per pixel are needed). :func:`fit_to_scene` first refits each candidate to the
pixels the scene shows (:mod:`gonio.fitting.selection.scene_fit`).
"""

# Presets: overcast, a uniform sky (constant emitter) and nothing else -- every direction
# lights the sample equally, so the specular lobe's shape integrates away; product-shot, a
# small area light and a dim fill, the preview's "area" lighting; close-up-sun, a directional
# sun and a dim sky, the camera close to the sample -- the highlight's shape fills the frame.
# CIEDE2000 through colour-science; the noise floor is
# gonio.fitting.render.preview.matched_noise_floor; the cost is Mitsuba's evaluation cost of
# the candidate's BSDF (seconds per 2^16 bsdf.eval calls, the best of three after the JIT's
# first call). front: the candidates no other one beats on both cost and error.
# Refusal: a candidate simpler than the chosen one whose noise floor is not below half the
# threshold and whose difference is not clear of the threshold by more than the floor.
# fit_to_scene: each candidate, started from its fit to the data, is refitted to the pixels
# the scene shows of the measured material, the direction pairs found by Mitsuba (camera
# rays, the scene's own light sampling), so a candidate is judged by what it can do in that
# scene rather than by its fit to every pair.

from __future__ import annotations

import time

import numpy as np

from gonio.core.channels import SRGB_Y
from gonio.models.mitsuba import select_variant

from gonio.fitting.selection.scene_fit import SAMPLE_ID
from gonio.fitting.render.preview import delta_e_2000, matched_noise_floor, measured_bsdf_dict

__all__ = ["PRESETS", "SAMPLE_ID", "scene_dict", "load_scene", "scene_pairs", "scene_samples", "sample_mask",
           "fit_to_scene", "render_in_scene", "rank_in_scene", "rendered_choice", "fallback_choice", "data_driven",
           "choose", "front"]

PRESETS = ("overcast", "product-shot", "close-up-sun")
_SUN = np.array([-0.45, 0.55, 0.7]) / np.linalg.norm([-0.45, 0.55, 0.7])   # toward the sun


def scene_dict(mi, preset, bsdf, size, spp):
    """The Mitsuba dict of a preset scene with ``bsdf`` on its sphere."""
    if preset not in PRESETS:
        raise ValueError(f"scene preset {preset!r}: choose one of {', '.join(PRESETS)} or give a Mitsuba scene file")
    close = preset == "close-up-sun"
    dist, fov = (2.6, 24.0) if close else (4.5, 30.0)
    scene = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
        "camera": {"type": "perspective", "fov": fov, "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, dist], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
    }
    if preset == "overcast":
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.8}}
    elif preset == "product-shot":
        scene["lamp"] = {"type": "sphere", "radius": 0.15, "center": [-2.9, 2.9, 3.5],
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 900.0}}}
        scene["fill"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.03}}
    else:
        scene["sun"] = {"type": "directional", "direction": (-_SUN).tolist(), "irradiance": {"type": "rgb", "value": 2.5}}
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.05}}
    return scene


def scene_samples(measured, preset, *, size=24, rng, k=16, rel_std=0.02, floor=1e-4, variant=None):
    """Measurements of the measured BSDF at the pairs the scene asks of it
    (:func:`gonio.fitting.selection.scene_fit.scene_pixels`), each pair weighted by the light it carries
    (the luminance of its radiance / pdf weight); a nominal sigma as rgl_samples. The pair fit
    these give is the start of :func:`fit_to_scene`'s pixel fit."""
    import mitsuba as mi

    from gonio.models.mitsuba import divide_cos, eval_cos

    from gonio.fitting.measurements import Measurements
    if not isinstance(rng, np.random.Generator):
        raise TypeError("scene_samples(rng=...) takes a numpy.random.Generator")
    variant = select_variant(variant)
    sp = scene_pairs(preset, size, rng=rng, k=k, variant=variant)
    with mi.scoped_set_variant(variant):
        bsdf = mi.load_dict(measured_bsdf_dict(measured, variant))
        f = divide_cos(eval_cos(bsdf, sp.wi, sp.wo, variant), sp.wi, sp.wo)
    std = rel_std * np.maximum(np.abs(f), floor)
    light = sp.weight @ np.array(SRGB_Y)
    attrs = {"source": f"scene {preset}", "nominal_sigma": True, "rel_std": rel_std, "floor": floor,
             "sampling": f"pairs the {preset} scene asks ({size} px, {k} light samples a pixel, weighted by the light)"}
    return Measurements(sp.wi, sp.wo, f, std, np.ones(f.shape, bool), attrs, weight=light * light.size / light.sum())


def load_scene(scene, bsdf, size, spp, variant=None):
    """``scene`` (a preset name or a Mitsuba XML scene file) loaded with ``bsdf`` (a Mitsuba
    dict) as the sample's material, the film ``size`` x ``size`` and ``spp`` samples a pixel.

    A scene file marks the sample's material ``<bsdf type="..." id="sample">`` (anywhere in the
    file); gonio puts each candidate's BSDF in its place and keeps everything else. Other
    files the scene names (meshes, textures) are found beside the scene file."""
    import mitsuba as mi

    select_variant(variant)
    bsdf = {**bsdf, "id": SAMPLE_ID}
    if str(scene) in PRESETS:
        return mi.load_dict(scene_dict(mi, str(scene), bsdf, int(size), int(spp)))
    text = _scene_file_with(scene, bsdf, int(size), int(spp))
    try:
        return mi.load_string(text)
    except RuntimeError as exc:
        raise ValueError(f"scene {scene}: Mitsuba cannot load it ({' '.join(str(exc).split())[:200]})") from None


def _scene_file_with(path, bsdf, size, spp) -> str:
    """The scene file's XML, checked (:func:`gonio.fitting.selection.scene_file.checked_scene`:
    confined to its folder, bounded), with the sample's BSDF replaced by ``bsdf`` and every
    sensor's film and sampler set (see :func:`load_scene`)."""
    import xml.etree.ElementTree as ET
    from pathlib import Path

    from gonio.fitting.formats.mitsuba_xml import _xml_lines
    from gonio.fitting.selection.scene_file import checked_scene

    path = Path(path)
    if path.suffix.lower() != ".xml" or not path.is_file():
        raise ValueError(f"scene {str(path)!r}: choose one of {', '.join(PRESETS)} or give a Mitsuba scene file (.xml)")
    root = checked_scene(path)
    parents = {c: p for p in root.iter() for c in p}
    found = [e for e in root.iter("bsdf") if e.get("id") == SAMPLE_ID]
    if len(found) != 1:
        raise ValueError(f"scene {path}: mark exactly one material <bsdf ... id=\"{SAMPLE_ID}\"> as the sample's "
                         f"(found {len(found)})")
    body = {k: v for k, v in bsdf.items() if k not in ("type", "id")}
    new = ET.fromstring("\n".join([f'<bsdf type="{bsdf["type"]}" id="{SAMPLE_ID}">', *_xml_lines(body, "  "),
                                    "</bsdf>"]))
    parent = parents[found[0]]
    parent[list(parent).index(found[0])] = new
    for sensor in root.iter("sensor"):           # a film or a size left out would be Mitsuba's 768 x 576
        if sensor.find("film") is None:
            ET.SubElement(sensor, "film", {"type": "hdrfilm"})
        if sensor.find("sampler") is None:
            ET.SubElement(sensor, "sampler", {"type": "independent"})
    for tag, name, value in (("film", "width", size), ("film", "height", size), ("sampler", "sample_count", spp)):
        for el in root.iter(tag):
            mine = [c for c in el.findall("integer") if c.get("name") == name]
            for child in mine or [ET.SubElement(el, "integer", {"name": name})]:
                child.set("value", str(int(value)))
    return ET.tostring(root, encoding="unicode")


def render_in_scene(bsdf, scene, size, spp, seeds, variant=None):
    """Renders of ``bsdf`` (a Mitsuba dict) in ``scene`` at each seed, linear RGB (size, size, 3)."""
    import mitsuba as mi

    variant = select_variant(variant)
    with mi.scoped_set_variant(variant):
        s = load_scene(scene, bsdf, int(size), int(spp), variant)
        return [np.array(mi.render(s, spp=int(spp), seed=int(seed)), dtype=np.float64)[..., :3] for seed in seeds]


def scene_pairs(scene, size, *, rng, k=64, variant=None):
    """The pixels of ``scene`` (a preset or a scene file, ``size`` x ``size``) that see the
    sample, with ``k`` light samples each (:func:`gonio.fitting.selection.scene_fit.scene_pixels`)."""
    import mitsuba as mi

    from gonio.fitting.selection.scene_fit import scene_pixels

    variant = select_variant(variant)
    with mi.scoped_set_variant(variant):
        return scene_pixels(load_scene(scene, {"type": "diffuse"}, size, 1, variant), rng=rng, k=k, name=str(scene))


def sample_mask(scene, size, variant=None) -> np.ndarray:
    """(size, size) bool: the pixels whose centre ray sees the sample (not the sky, the lamp or
    another object), the pixels :func:`rank_in_scene` compares."""
    return scene_pairs(scene, size, rng=np.random.default_rng(0), k=1, variant=variant).mask


def fit_to_scene(fits, measured, scene, *, size=32, k=64, rng, variant=None):
    """Each candidate of ``fits`` (FitResults, their parameters the starts) refitted to the
    scene's pixels of the measured material (:mod:`gonio.fitting.selection.scene_fit`): the fit a
    scene asks for. Returns a list of :class:`~gonio.fitting.selection.scene_fit.SceneFit`."""

    from gonio.fitting.selection.scene_fit import fit_in_scene, measured_pixels

    if not isinstance(rng, np.random.Generator):
        raise TypeError("fit_to_scene(rng=...) takes a numpy.random.Generator")
    variant = select_variant(variant)
    sp = scene_pairs(scene, size, rng=rng, k=k, variant=variant)
    target = measured_pixels(measured, sp, variant)
    return [fit_in_scene(res.model, sp, target, rng=rng, start=res.params) for res in fits]


def eval_cost(bsdf, variant=None, n=1 << 16):
    """Seconds per ``n`` Mitsuba ``bsdf.eval`` calls (the best of three, after a first call)."""
    import mitsuba as mi

    from gonio.models.mitsuba import eval_cos

    variant = select_variant(variant)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2])
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    with mi.scoped_set_variant(variant):
        b = mi.load_dict(bsdf)
        eval_cos(b, v[0], v[1], variant)
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            eval_cos(b, v[0], v[1], variant)
            best = min(best, time.perf_counter() - t0)
    return best


def rendered_choice(ranking, measured=None, *, scene="product-shot", size=32, spp=128, seed=0, threshold=1.0,
                    variant=None, fallback=None, progress=None):
    """``--model auto`` without a scene: the data's evidence and a default scene together.

    BIC (:func:`gonio.fitting.select`) ranks the candidates by the data's evidence. The
    reference is the measured material where it can be rendered (``measured``: an RGL / MERL
    path or a Mitsuba dict), else the candidate the data supports best (lowest BIC). Every
    candidate no more complex than BIC's choice is rendered beside the reference in ``scene``
    with matched seeds (:func:`rank_in_scene`), and the simplest one within ``threshold``
    (:func:`choose`) is chosen: a model the data can tell apart but the scene cannot is not
    needed there. Without a candidate within the threshold, or when the renders' noise cannot
    tell, BIC's choice stands. Each rendered row of ``ranking`` gets ``delta_e`` and ``noise``.

    When the reference is the measured material and no candidate up to BIC's choice renders
    within ``threshold`` (:func:`fallback_choice`), the data's evidence has not found a model
    the scene accepts: the more complex candidates already fitted are rendered too, and
    ``fallback`` (a callable returning further FitResults, e.g. :func:`data_driven` fitting
    the tabulated model from the data) is called and its fits rendered and added to
    ``ranking``; the simplest row within the threshold is then chosen, else the row rendering
    closest to the measured material where it is clearly closer than BIC's choice (by more
    than the two rows' noise floors together), else BIC's choice stands.

    Returns ``(result, ranking, note)``: the chosen FitResult, the ranking with ``chosen``
    moved, and a line saying what decided. ``progress``: as :func:`rank_in_scene`'s.
    """
    by_bic = next(r for r in ranking if r.chosen)
    best = min(ranking, key=lambda r: r.bic)
    rows = [r for r in ranking if r.k <= by_bic.k]
    try:    # a reference Mitsuba cannot render (no twin, or not in this variant): BIC's choice stands
        reference = measured if measured is not None else best.result.model.to_mitsuba(best.result.params)
        ranked = rank_in_scene([r.result for r in rows], reference, scene, size=size, spp=spp, seed=seed,
                               threshold=threshold, variant=variant, progress=progress)
    except ValueError as exc:
        return by_bic.result, ranking, f"BIC's choice stands: {exc}"
    for r, rr in zip(rows, ranked["rows"]):
        r.delta_e, r.noise = rr["delta_e"], rr["noise"]
    pick = ranked["chosen"]
    what = "the measured material" if measured is not None else f"the best-supported fit ({best.name})"
    if pick is None and measured is not None:
        return fallback_choice(ranking, rows, by_bic, measured, scene=scene, size=size, spp=spp, seed=seed,
                               threshold=threshold, variant=variant, fallback=fallback, progress=progress)
    if pick is None:
        return by_bic.result, ranking, (f"BIC's choice stands: no candidate up to it renders within CIEDE2000 "
                                        f"{threshold:g} of {what} in the {scene} scene")
    chosen = rows[ranked["rows"].index(pick)]
    if chosen is by_bic:
        return by_bic.result, ranking, (f"BIC's choice, and no simpler candidate renders within CIEDE2000 "
                                        f"{threshold:g} of {what} in the {scene} scene")
    by_bic.chosen, chosen.chosen = False, True
    return chosen.result, ranking, (f"{chosen.name} (k = {chosen.k}) renders within CIEDE2000 {threshold:g} of "
                                    f"{what} in the {scene} scene ({chosen.delta_e:.2f}, floor {chosen.noise:.2f}): "
                                    f"simpler than BIC's {by_bic.name} (k = {by_bic.k}), which the scene does not need")


def fallback_choice(ranking, rendered, by_bic, measured, *, scene, size, spp, seed, threshold, variant=None,
                    fallback=None, progress=None):
    """:func:`rendered_choice` where no candidate up to BIC's choice (``rendered``, rows of
    ``ranking`` with ``delta_e`` set) renders within ``threshold`` of the measured material:
    render the more complex candidates of ``ranking`` and ``fallback()``'s fits (added to
    ``ranking`` as rows of their own, BIC beside the others'), then choose the simplest
    within the threshold (:func:`choose`), else the closest where it is clearly closer than
    BIC's choice (its difference lower by more than both noise floors), else BIC's choice.
    Returns ``(result, ranking, note)`` as :func:`rendered_choice`."""
    from gonio.fitting.selection.by_data import Ranked

    t0 = time.perf_counter()
    more = [r for r in ranking if r.k > by_bic.k]
    if progress is not None and fallback is not None:
        progress(0, None, "fitting the fallback")
    extra = list(fallback()) if fallback is not None else []
    best_bic = min(r.bic for r in ranking)
    for res in extra:
        ranking.append(Ranked(res.model.name, dict(res.model.options), res.space.size, res.chi2, res.bic,
                              0.0, False, res, res.loss, res.neg2_loglik))
    added = more + ranking[len(ranking) - len(extra):]
    if added:
        ranked = rank_in_scene([r.result for r in added], measured, scene, size=size, spp=spp, seed=seed,
                               threshold=threshold, variant=variant, progress=progress)
        for r, rr in zip(added, ranked["rows"]):
            r.delta_e, r.noise = rr["delta_e"], rr["noise"]
    best_bic = min(best_bic, *(r.bic for r in ranking))
    for r in ranking:
        r.delta_bic = r.bic - best_bic
    ranking.sort(key=lambda r: r.bic)
    cost = f"; the fallback's fits took {sum(r.time_s for r in extra):.1f} s" if extra else ""
    rows = rendered + added
    table = [{"model": r.name, "k": r.k, "delta_e": r.delta_e, "noise": r.noise, "chosen": False, "row": r}
             for r in rows]
    try:
        good = choose(table, threshold, f"scene {scene}", spp)
    except ValueError:
        good = None
    if good is not None:
        chosen = good["row"]
        why = f"renders within CIEDE2000 {threshold:g} of"
    else:
        chosen = min(rows, key=lambda r: r.delta_e)
        if chosen is by_bic or by_bic.delta_e - chosen.delta_e <= by_bic.noise + chosen.noise:
            return by_bic.result, ranking, (f"BIC's choice stands: no candidate renders within CIEDE2000 "
                                            f"{threshold:g} of the measured material in the {scene} scene, and "
                                            f"none clearly closer than it ({by_bic.delta_e:.2f}){cost}")
        why = f"renders closest (none within CIEDE2000 {threshold:g}; BIC's {by_bic.name} {by_bic.delta_e:.2f}) to"
    by_bic.chosen, chosen.chosen = False, True
    return chosen.result, ranking, (f"{chosen.name} (k = {chosen.k}) {why} the measured material in the "
                                    f"{scene} scene ({chosen.delta_e:.2f}, floor {chosen.noise:.2f}){cost}; "
                                    f"the fallback took {time.perf_counter() - t0:.1f} s")


def data_driven(meas, *, seed=0, loss=None):
    """A ``fallback`` for :func:`rendered_choice`: the data-driven ``tabulated`` model fitted
    from the data (:func:`gonio.fitting.fit_tabulated`), not a ``--model auto`` candidate
    (42 numbers), fitted only when no candidate renders within the threshold."""
    from gonio.fitting.likelihood.loss import REAL_DEFAULT_LOSS
    from gonio.fitting.optimise.tabulated_start import fit_tabulated

    return lambda: [fit_tabulated(meas, rng=np.random.default_rng([seed, 16]), loss=loss or REAL_DEFAULT_LOSS)]


def choose(rows, threshold, what="scene", spp=None):
    """The simplest row (fewest parameters ``k``, then the closest: a timing would make the
    choice irreproducible) whose ``delta_e`` is below
    ``threshold`` with a ``noise`` floor under half of it, flagged ``chosen``; None if every
    row is clearly worse. Simplest first, each row is good, bad (above the threshold, or clear
    of it by more than its floor) or unclear: an unclear row before the chosen one raises
    ValueError (more samples per pixel are needed to tell)."""
    for r in sorted(rows, key=lambda r: (r["k"], r["delta_e"])):
        floor_ok = r["noise"] < 0.5 * threshold
        if floor_ok and r["delta_e"] < threshold:
            r["chosen"] = True
            return r
        if not (floor_ok or r["delta_e"] - r["noise"] > threshold):
            raise ValueError(f"{what}: the noise floor of the comparison ({r['noise']:.2f} CIEDE2000 for "
                             f"{r['model']}) is not below half the threshold {threshold:g}: raise spp"
                             + (f" (now {spp})" if spp else ""))
    return None


def front(rows):
    """The speed-versus-error front: rows no other row beats on both cost and error."""
    return [r for r in rows if not any((o["cost_s"] <= r["cost_s"] and o["delta_e"] < r["delta_e"])
                                       or (o["cost_s"] < r["cost_s"] and o["delta_e"] <= r["delta_e"]) for o in rows)]


def rank_in_scene(fits, measured, scene, *, size=32, spp=16, seed=0, threshold=1.0, variant=None, progress=None):
    """Rank fitted candidates by their rendered difference from the measured BSDF in a scene.

    Parameters
    ----------
    fits : sequence of FitResult
        The fitted candidates (e.g. every row of ``select``'s ranking).
    measured : Mitsuba BSDF dict, RGL ``.bsdf`` / MERL ``.binary`` path, RGLBRDF or MerlBRDF
        The measured material.
    scene : str
        A preset (:data:`PRESETS`); anything else is refused (ValueError).
    size, spp, seed : int
        Render size (pixels, square), samples per pixel, the first seed (seed + 1 for the
        noise floor's second pair).
    threshold : float
        Mean CIEDE2000 below which a candidate is good enough.
    progress : callable, optional
        ``progress(done, total, label)`` before each render and at the end.

    Returns
    -------
    dict
        ``rows`` (one per candidate: model, options, k, delta_e, noise, cost_s, chosen),
        ``front`` (the speed-versus-error front, cheapest first), ``chosen`` (the row, or
        None when no candidate is below the threshold), ``scene``, ``size``, ``spp``, ``seed``,
        ``threshold``.
    """
    if not fits:
        raise ValueError("rank_in_scene: no fitted candidates")
    variant = select_variant(variant)
    if progress is not None:
        progress(0, len(fits) + 1, f"rendering the reference in {scene}")
    meas_bsdf = measured_bsdf_dict(measured, variant)
    ref_a, ref_b = render_in_scene(meas_bsdf, scene, size, spp, (seed, seed + 1), variant)
    # the pixels that see the sample: a visible sky or lamp would add pixels every candidate
    # gets right and dilute the mean
    seen = sample_mask(scene, size, variant)
    rows = []
    for k, res in enumerate(fits):
        if progress is not None:
            progress(k + 1, len(fits) + 1, f"rendering {res.model.name}")
        bsdf = res.model.to_mitsuba(res.params)
        img_a, img_b = render_in_scene(bsdf, scene, size, spp, (seed, seed + 1), variant)
        de = delta_e_2000(img_a, ref_a)[seen]
        noise = matched_noise_floor(img_a, ref_a, img_b, ref_b)[seen]
        rows.append({"model": res.model.name, "options": dict(res.model.options), "k": int(res.space.size),
                     "delta_e": float(de.mean()), "noise": float(noise.mean()), "cost_s": eval_cost(bsdf, variant),
                     "chosen": False})
    if progress is not None:
        progress(len(fits) + 1, len(fits) + 1, "rendered")
    chosen = choose(rows, threshold, f"scene {scene}", spp)
    return {"rows": rows, "front": sorted(front(rows), key=lambda r: r["cost_s"]), "chosen": chosen,
            "scene": str(scene), "size": int(size), "spp": int(spp), "seed": int(seed), "threshold": float(threshold)}
