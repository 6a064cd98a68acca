"""One self-contained HTML report of a session: capture, fit, and the Mitsuba loop closure.

The report reads what the other commands wrote (``dataset.nc``, ``fit.json``,
``render/render.json``) and embeds matplotlib PNGs as base64, so the single file reads
offline; the PNGs are also written beside it for reuse.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from .errors import GonioError

__all__ = ["find_outputs", "write_report"]


def find_outputs(folder) -> dict:
    """Locate the dataset, fit file and render summary under ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise GonioError(f"{folder} is not a folder; give the output folder of `gonio demo` or a session folder")

    def first(*patterns):
        for pattern in patterns:
            hits = sorted(folder.glob(pattern))
            if hits:
                return hits[0]
        return None

    found = {"dataset": first("dataset.nc", "*/dataset.nc"), "fit": first("fit.json", "*/fit.json"),
             "render": first("render/render.json", "render.json", "*/render.json"),
             "preview": first("render/preview/preview.json", "preview/preview.json", "*/preview/preview.json"),
             "speed": first("speed.json", "*/speed.json")}
    if found["dataset"] is None:
        raise GonioError(f"no dataset.nc under {folder}; run `gonio export SESSION` first")
    return found


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


def _fmt(v, digits=4):
    if v is None:
        return "–"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x, digits) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return html.escape(str(v))


def _truth_by_name(truth, names):
    """Map fit-vector names (``diffuse_reflectance[R]``) to true values where the truth is known."""
    if not truth or "params" not in truth:
        return {}
    out = {}
    channels = ["R", "G", "B"]
    for name in names:
        base, _, chan = name.partition("[")
        if base not in truth["params"]:
            continue
        value = np.asarray(truth["params"][base], dtype=float).reshape(-1)
        if chan:
            c = channels.index(chan.rstrip("]"))
            out[name] = float(value[c] if value.size > 1 else value[0])
        else:
            out[name] = float(value[0])
    return out


def _plan_text(plan):
    if not plan:
        return None
    try:
        doc = json.loads(plan) if isinstance(plan, str) else plan
    except json.JSONDecodeError:
        return str(plan)[:200]
    points = doc.get("points") or doc.get("angles") or []
    return f"{doc.get('name', '?')}: {len(points)} points. {doc.get('description', '')}".strip()


def _truth_text(truth):
    if not isinstance(truth, dict):
        return None
    return f"{truth.get('model', truth.get('bsdf_file', '?'))} {json.dumps(truth.get('options', {}))} {json.dumps(truth.get('params', {}))}"


def _reciprocity(dataset_path, meas):
    """Median relative difference between reciprocal partners (wi and wo swapped), or None."""
    import xarray as xr

    with xr.open_dataset(dataset_path, engine="h5netcdf") as ds:
        if "reciprocal_partner" not in ds.variables:
            return None
        partner = np.asarray(ds["reciprocal_partner"].values, dtype=int)
    i = np.where((partner > np.arange(partner.size)) & (partner < partner.size))[0]
    if i.size == 0:
        return None
    a, b = meas.brdf[i], meas.brdf[partner[i]]
    rel = np.abs(a - b) / np.maximum(0.5 * np.abs(a + b), 1e-12)
    return f"{float(np.median(rel)):.2e} over {i.size} pairs (max {float(rel.max()):.2e})"


def write_report(folder, out=None) -> Path:
    """Write the HTML report for ``folder``; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gonio.fitting import load_dataset, load_fit
    from gonio.fitting._io import atomic_open

    from .fit_runner import _energy_text

    found = find_outputs(folder)
    out = Path(out) if out else Path(folder) / "report.html"
    meas = load_dataset(found["dataset"])
    theta_i = np.degrees(np.arccos(np.clip(meas.wi[:, 2], -1, 1)))
    theta_o = np.degrees(np.arccos(np.clip(meas.wo[:, 2], -1, 1)))
    phi_i = np.arctan2(meas.wi[:, 1], meas.wi[:, 0])
    phi_o = np.arctan2(meas.wo[:, 1], meas.wo[:, 0])
    images: dict[str, bytes] = {}
    sections: list[str] = []
    colours = ["tab:red", "tab:green", "tab:blue"]

    # ---- capture summary and coverage
    attrs = meas.attrs
    summary_rows = [("points", meas.n_points), ("usable values", meas.n_used), ("seed", attrs.get("seed")),
                    ("plan", _plan_text(attrs.get("plan"))), ("sample (simulated truth)", _truth_text(attrs.get("sample_truth"))),
                    ("reciprocity (median |f_a - f_b| / mean over pairs)", _reciprocity(found["dataset"], meas)),
                    ("capture wall time, first to last point (s)", attrs.get("capture_wall_s")),
                    ("lamp drift over the session (monitor span / median)", attrs.get("lamp_drift")),
                    ("reference scale uncertainty (relative 1-sigma)", attrs.get("scale_rel_std")),
                    ("gonio version", attrs.get("gonio_version"))]
    sections.append("<h2>Capture</h2><table>" + "".join(
        f"<tr><th>{html.escape(k)}</th><td>{_fmt(v)}</td></tr>" for k, v in summary_rows if v is not None) + "</table>")
    fig, ax = plt.subplots(subplot_kw={"projection": "polar"}, figsize=(4.4, 4.4))
    sc = ax.scatter(phi_o, theta_o, c=theta_i, cmap="viridis", s=14)
    ax.set_ylim(0, 90)
    ax.set_rticks([30, 60, 90])
    ax.set_title("detector directions (r = theta_o, colour = theta_i)", fontsize=9)
    fig.colorbar(sc, ax=ax, shrink=0.7, label="theta_i (deg)")
    images["coverage.png"] = _png(fig)

    fit_doc = model = params = None
    if found["fit"] is not None:
        model, params, fit_doc = load_fit(found["fit"])

    # ---- fit: parameter table, goodness, selection
    if fit_doc is not None:
        truth = attrs.get("sample_truth") if isinstance(attrs.get("sample_truth"), dict) else None
        names = list(fit_doc["parameters"])
        truths = _truth_by_name(truth, names) if truth and truth.get("model") == fit_doc["model"]["name"] else {}
        rows = []
        for name, p in fit_doc["parameters"].items():
            t = truths.get(name)
            z = (p["value"] - t) / p["std"] if (t is not None and p["std"]) else None
            flags = ", ".join(f for f, on in (("at bound", p["at_bound"]), ("undetermined", p["undetermined"])) if on)
            rows.append(f"<tr><td>{html.escape(name)}</td><td>{_fmt(p['value'])}</td><td>{_fmt(p['std'], 2)}</td>"
                        f"<td>{_fmt(p['ci90'], 7)}</td><td>{_fmt(t)}</td><td>{_fmt(z, 2)}</td><td>{html.escape(p['unit'] or '')}</td>"
                        f"<td>{html.escape(p['method'])}</td><td>{flags}</td></tr>")
        g = fit_doc["goodness"]
        sections.append(
            f"<h2>Fit: {html.escape(fit_doc['model']['name'])} {html.escape(json.dumps(fit_doc['model']['options']))}</h2>"
            "<table><tr><th>parameter</th><th>value</th><th>1-sigma</th><th>90 % interval</th><th>truth</th>"
            "<th>(value-truth)/sigma</th><th>unit</th><th>method</th><th>flags</th></tr>" + "".join(rows) + "</table>"
            f"<p>chi<sup>2</sup>/dof = {_fmt(g['chi2_dof'])} ({g['dof']} dof); RMSE f_r = {_fmt(g['rmse_fr'])} sr<sup>-1</sup>; "
            f"RMSE cos-weighted = {_fmt(g['rmse_cos_fr'])}; optimiser {html.escape(fit_doc['optimiser']['method'])}, "
            f"{fit_doc['optimiser']['evaluations']} evaluations, {_fmt(fit_doc['optimiser']['time_s'], 3)} s. "
            f"Energy: {html.escape(_energy_text(fit_doc['constraints']['energy']))}.</p>")
        if fit_doc.get("posterior"):
            post = fit_doc["posterior"]
            sections.append(f"<p>Posterior (emcee): {post['walkers']} walkers x {post['steps']} steps, "
                            f"{_fmt(post['independent_samples'], 3)} independent samples, converged: {post['converged']}. "
                            f"{html.escape(post.get('advice') or '')}</p>")
        if fit_doc.get("selection"):
            sections.append("<h3>Model selection (BIC)</h3><table><tr><th>model</th><th>k</th><th>chi<sup>2</sup></th>"
                            "<th>&Delta;BIC</th><th>chosen</th></tr>" + "".join(
                                f"<tr><td>{html.escape(r['model'])} {html.escape(json.dumps(r['options']))}</td><td>{r['k']}</td>"
                                f"<td>{_fmt(r['chi2'])}</td><td>{_fmt(r['delta_bic'], 3)}</td><td>{'yes' if r['chosen'] else ''}</td></tr>"
                                for r in fit_doc["selection"]) + "</table>")

        # ---- measured vs fitted, in the plane of incidence, for several incidence angles
        fitted = model.eval(meas.wi, meas.wo, params)
        resid = (meas.brdf - fitted) / meas.brdf_std
        phi_d = np.degrees(np.abs(np.angle(np.exp(1j * (phi_i - phi_o)))))
        in_plane = (phi_d > 175) | (phi_d < 5) | (theta_i < 1) | (theta_o < 1)
        incidences = sorted({round(t) for t in theta_i[in_plane]})
        if incidences:
            pick = incidences if len(incidences) <= 4 else [incidences[int(k)] for k in np.linspace(0, len(incidences) - 1, 4)]
            fig, axes = plt.subplots(1, len(pick), figsize=(3.3 * len(pick), 3.2), squeeze=False)
            for ax, ti in zip(axes[0], pick):
                sel = in_plane & (np.abs(theta_i - ti) < 0.6)
                # signed outgoing angle: negative on the lamp's side
                signed = np.where(phi_d[sel] < 90, -theta_o[sel], theta_o[sel])
                t = np.radians(np.linspace(-89, 89, 241))
                wi_c = np.tile([np.sin(np.radians(ti)), 0.0, np.cos(np.radians(ti))], (t.size, 1))
                wo_c = np.stack([-np.sin(t), np.zeros_like(t), np.cos(t)], axis=-1)  # +t on the mirror side
                curve = model.eval(wi_c, wo_c, params)
                for c in range(meas.n_channels):
                    ax.errorbar(signed, meas.brdf[sel, c], yerr=meas.brdf_std[sel, c], fmt="o", ms=3, color=colours[c % 3])
                    ax.plot(np.degrees(t), curve[:, c], "-", lw=1, color=colours[c % 3])
                ax.set_yscale("log")
                ax.set_title(f"theta_i = {ti} deg (in plane)", fontsize=9)
                ax.set_xlabel("theta_o (deg, + = mirror side)")
            axes[0][0].set_ylabel("f_r (1/sr)")
            images["inplane.png"] = _png(fig)
        # polar view at the incidence with the most out-of-plane points: the fit over the whole
        # hemisphere (background), the measurements on the same colour scale (dots)
        out_of_plane = ~in_plane
        if out_of_plane.any():
            groups, counts = np.unique(np.round(theta_i[out_of_plane]), return_counts=True)
            ti = float(groups[np.argmax(counts)])
            sel = np.abs(theta_i - ti) < 0.6
            phi_in = float(np.median(phi_i[sel]))
            t, p = np.meshgrid(np.radians(np.linspace(0, 85, 60)), np.radians(np.linspace(-180, 180, 121)))
            wo_g = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
            wi_g = np.tile([np.sin(np.radians(ti)) * np.cos(phi_in), np.sin(np.radians(ti)) * np.sin(phi_in),
                            np.cos(np.radians(ti))], (wo_g.shape[0], 1))
            c = 1 if meas.n_channels > 1 else 0
            grid = model.eval(wi_g, wo_g, params)[:, c].reshape(t.shape)
            norm = matplotlib.colors.LogNorm(vmin=max(float(grid.min()), 1e-4), vmax=float(grid.max()))
            fig, axes = plt.subplots(1, 2, subplot_kw={"projection": "polar"}, figsize=(8.4, 4.0))
            for ax, title in zip(axes, ("fit (background) and measurement (dots)", "measurement / fit")):
                ax.set_ylim(0, 85)
                ax.set_title(title, fontsize=9)
            mesh = axes[0].pcolormesh(p, np.degrees(t), grid, norm=norm, cmap="viridis", shading="auto")
            axes[0].scatter(phi_o[sel], theta_o[sel], c=meas.brdf[sel, c], norm=norm, cmap="viridis",
                            edgecolors="white", s=28)
            fig.colorbar(mesh, ax=axes[0], shrink=0.7, label=f"f_r {meas.channels[c]} (1/sr)")
            ratio = meas.brdf[sel, c] / np.maximum(fitted[sel, c], 1e-12)
            sc = axes[1].scatter(phi_o[sel], theta_o[sel], c=ratio, cmap="coolwarm", s=28,
                                 vmin=1 - 3 * float(np.std(ratio - 1) + 1e-6), vmax=1 + 3 * float(np.std(ratio - 1) + 1e-6))
            fig.colorbar(sc, ax=axes[1], shrink=0.7)
            fig.suptitle(f"theta_i = {ti:.0f} deg", fontsize=9)
            images["polar.png"] = _png(fig)
        fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
        axes[0].hist(resid[meas.use].ravel(), bins=40, color="grey")
        axes[0].set_xlabel("(measured - fit) / sigma")
        axes[0].set_title("fit residuals", fontsize=9)
        sc = axes[1].scatter(theta_i, theta_o, c=np.sqrt(np.mean(resid ** 2, axis=1)), cmap="magma", s=16)
        axes[1].set_xlabel("theta_i (deg)")
        axes[1].set_ylabel("theta_o (deg)")
        axes[1].set_title("rms residual / sigma per point", fontsize=9)
        fig.colorbar(sc, ax=axes[1])
        images["residuals.png"] = _png(fig)
        # directional albedo of the fit
        t = np.radians(np.linspace(0, 85, 35))
        wo_a = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], axis=-1)
        alb = model.albedo(wo_a, params)
        fig, ax = plt.subplots(figsize=(4.2, 3.0))
        for c in range(alb.shape[1]):
            ax.plot(np.degrees(t), alb[:, c], color=colours[c % 3])
        ax.set_xlabel("theta_o (deg)")
        ax.set_ylabel("directional albedo")
        ax.set_ylim(0, max(1.05, float(alb.max()) * 1.05))
        images["albedo.png"] = _png(fig)

    # ---- posterior corner plot
    post = (fit_doc or {}).get("posterior") or {}
    if post.get("samples"):
        import corner

        samples = np.asarray(post["samples"], dtype=float)
        fig = corner.corner(samples, labels=post.get("names"), quantiles=[0.05, 0.5, 0.95], label_kwargs={"fontsize": 8})
        fig.suptitle("posterior (emcee)" + ("" if post.get("converged") else ": chain too short, see advice"), fontsize=9)
        images["corner.png"] = _png(fig)

    # ---- speed against error on this capture
    if found["speed"] is not None:
        sp = json.loads(Path(found["speed"]).read_text())
        sections.append(f"<h2>Fit speed against error ({sp['points']} points, {html.escape(sp['model'])})</h2>"
                        "<table><tr><th>optimiser</th><th>time (s)</th><th>evaluations</th><th>chi<sup>2</sup></th>"
                        "<th>max |fit - truth| / sigma</th><th>RMSE f_r</th></tr>" + "".join(
                            f"<tr><td>{html.escape(r['optimiser'])}</td><td>{_fmt(r['time_s'], 3)}</td><td>{r['evaluations']}</td>"
                            f"<td>{_fmt(r['chi2'])}</td><td>{_fmt(r['max_pull'], 3)}</td><td>{_fmt(r['rmse_fr'], 3)}</td></tr>"
                            for r in sp["rows"]) + "</table>")

    # ---- Mitsuba loop closure
    if found["render"] is not None:
        rd = json.loads(Path(found["render"]).read_text())
        s = rd["summary"]
        sc = rd.get("scene_check") or {}
        sections.append(
            "<h2>Mitsuba re-render at the measured geometry</h2>"
            f"<p>variant {html.escape(rd['variant'])}, {rd['points']} points in {_fmt(rd['time_s'], 3)} s "
            f"(one batched evaluation; {sc.get('poses', 0)} poses re-rendered as full scenes in "
            f"{html.escape(str(sc.get('variant')))} agree to {_fmt(sc.get('max_rel'), 2)}). "
            f"Export check: max |render - model| / model = {_fmt(s['export_max_rel'])}. "
            f"Render vs measurement: rms residual {_fmt(s['residual_rms_sigma'], 3)} sigma, "
            f"max |residual| {_fmt(s['residual_max_sigma'], 3)} sigma.</p>"
            "<table><tr><th>worst points</th><th>theta_i</th><th>phi_i</th><th>theta_o</th><th>phi_o</th><th>residual / sigma</th></tr>"
            + "".join(f"<tr><td>{w['point']}</td><td>{_fmt(w['theta_i'], 3)}</td><td>{_fmt(w['phi_i'], 3)}</td>"
                      f"<td>{_fmt(w['theta_o'], 3)}</td><td>{_fmt(w['phi_o'], 3)}</td><td>{_fmt(w['residual_sigma'], 3)}</td></tr>"
                      for w in s["worst"]) + "</table>")
        rendered = np.asarray(rd["brdf_render"])
        fig, ax = plt.subplots(figsize=(4.2, 4.0))
        for c in range(min(3, rendered.shape[1])):
            ax.loglog(meas.brdf[:, c], rendered[:, c], "o", ms=3, color=colours[c])
        lim = [max(1e-4, float(np.min(meas.brdf[meas.brdf > 0])) * 0.8), float(np.max(meas.brdf)) * 1.2]
        ax.plot(lim, lim, "k--", lw=0.8)
        ax.set_xlabel("measured f_r (1/sr)")
        ax.set_ylabel("Mitsuba render of the fit (1/sr)")
        images["mitsuba_vs_measured.png"] = _png(fig)

    # ---- preview renders
    if found["preview"] is not None:
        pv = json.loads(Path(found["preview"]).read_text())
        rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v.get('mean'), 3)}</td><td>{_fmt(v.get('p95'), 3)}</td>"
                       f"<td>{_fmt(v.get('noise_mean'), 3)}</td></tr>" for k, v in (pv.get("delta_e") or {}).items())
        sections.append("<h2>Preview renders</h2>"
                        f"<p>Sphere, {pv.get('size')} px, {pv.get('spp')} spp, {html.escape(str(pv.get('variant')))}, "
                        f"{_fmt(pv.get('time_s'), 3)} s. Left: the fit; right: the measured (or true simulated) BSDF; "
                        "then the CIEDE2000 difference.</p>"
                        + ("<table><tr><th>lighting</th><th>mean &Delta;E00</th><th>95th pct</th>"
                           f"<th>Monte Carlo noise floor (mean)</th></tr>{rows}</table>" if rows else ""))
        side = pv.get("side_by_side_png")
        if side and Path(side).exists():
            images["preview_side_by_side.png"] = Path(side).read_bytes()

    # ---- the fit as a Mitsuba scene snippet
    if fit_doc is not None:
        from gonio.fitting.formats import mitsuba_snippet

        xml, _ = mitsuba_snippet(model.name, dict(model.options), params)
        sections.append("<h2>Use the fit in Mitsuba 3</h2><pre>" + html.escape(xml) + "</pre>"
                        f"<pre>{html.escape(json.dumps(fit_doc['mitsuba'], indent=1))}</pre>")

    # ---- assemble
    image_dir = out.with_name(out.stem + "_files")
    image_dir.mkdir(parents=True, exist_ok=True)
    figures = []
    for name, data in images.items():
        (image_dir / name).write_bytes(data)
        figures.append(f'<figure><img alt="{name}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'
                       f"<figcaption>{name}</figcaption></figure>")
    page = ("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>gonio report</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
            "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}"
            "figure{display:inline-block;margin:0.5em}img{max-width:100%}</style></head><body>"
            f"<h1>gonio report: {html.escape(str(Path(folder).resolve().name))}</h1>"
            + "".join(sections) + "<h2>Figures</h2>" + "".join(figures)
            # After load, record how many images the browser decoded (the headless-browser test reads it).
            + "<script>window.addEventListener('load',function(){var im=Array.prototype.slice.call(document.images);"
              "document.body.setAttribute('data-images-decoded',im.filter(function(i){return i.complete&&i.naturalWidth>0;})"
              ".length+'/'+im.length);});</script></body></html>")
    with atomic_open(out, "w") as fh:
        fh.write(page)
    return out
