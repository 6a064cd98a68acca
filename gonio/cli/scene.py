"""``gonio fit DATA --scene SCENE``: the CLI side of `gonio.fitting.for_scene` (open the
dataset, check the output, call, write, print the scene's table)."""

from __future__ import annotations

from pathlib import Path

from gonio.fitting.for_scene import TIME_LIMIT_S, check_scene_options, fit_for_scene, option_text

__all__ = ["check_scene_options", "fit_scene_cli", "print_scene", "TIME_LIMIT_S"]


def fit_scene_cli(dataset: Path, *, scene, model, options, out: Path, seed, loss, size=32, spp=256, k=64,
                  threshold=1.0, time_limit=TIME_LIMIT_S, quiet=False):
    from gonio.fitting import write_json_atomic

    from gonio.core.preflight import check_output_file, writing
    from gonio.cli.fit import _open_dataset, _wrapped, print_selection
    from gonio.cli.progress import Steps

    check_scene_options(scene, dataset, size, spp, k, threshold, time_limit)
    check_output_file(out, "fit file (--out)")
    meas = _open_dataset(dataset, seed)
    with Steps(f"fit for the scene {scene}", enabled=not quiet):
        doc, ranking = fit_for_scene(meas, dataset, scene=scene, model=model, options=options, seed=seed, loss=loss,
                                     size=size, spp=spp, k=k, threshold=threshold, time_limit=time_limit)
    with writing(out):
        write_json_atomic(out, doc)
    print_scene(doc)
    print_selection(doc)
    chosen = next(r for r in doc["scene"]["rows"] if r["chosen"])
    by_bic = next(r for r in ranking if r.chosen)
    _wrapped(f"chosen for scene {scene}: {chosen['model']}{option_text(chosen)} (k = {chosen['k']}); by the data "
             f"alone (BIC): {by_bic.name}{option_text({'options': by_bic.options})} (k = {by_bic.k})")
    print(f"wrote {out}")


def print_scene(doc, console=None) -> None:
    """The scene's table: each candidate's rendered difference against its Mitsuba cost."""
    from rich.console import Console

    from gonio.cli.console import print_table

    s = doc["scene"]
    rows = [[r["model"] + option_text(r), str(r["k"]), f"{r['delta_e']:.2f}", f"{r['noise']:.2f}",
             f"{r['cost_s'] * 1e3:.2f}", "front" if r["on_front"] else "", "*" if r["chosen"] else ""]
            for r in sorted(s["rows"], key=lambda r: r["cost_s"])]
    print_table(console or Console(), [("model", "left"), ("k", "right"), ("dE00", "right"), ("noise", "right"),
                                       ("ms/65536 evals", "right"), ("", "left"), ("", "left")], rows,
                title=f"scene {s['scene']}: rendered difference (mean CIEDE2000, {s['spp']} spp) against Mitsuba cost",
                caption=f"* chosen: the simplest candidate below {s['threshold']:g}; front: no other candidate is "
                        "both cheaper and closer")
