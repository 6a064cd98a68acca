import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import sys, math, json, pickle
from pathlib import Path
import numpy as np
from analyse import analyse
import budget_coverage as BC
import gonio.sim
from gonio.bench.settings import default_settings
from gonio.bench.calibrate import merge_calibration
from gonio.cli.capture import _reference_for
from gonio.bench.measure.point import ReferenceModel
from gonio.fitting.likelihood.aperture import aperture_mean
from gonio.core.geometry import directions as dirs

def recon(sample, seed):
    out, A = analyse(sample, seed, nmc=10, verbose=False)
    d = pickle.load(open(f"{WORK}/rec-{sample}-{seed}.pkl", "rb"))
    settings = default_settings(); settings["errors"] = {"preset": "typical"}
    settings = merge_calibration(settings, A["cal"])
    spec, options, shape, plan = BC.CAPTURE_SAMPLES[sample]
    inst = gonio.sim.Instrument(settings, sample=spec, reference=_reference_for(settings), seed=seed)
    st = inst.error_state
    rows = A["rows"]; N = len(rows)
    t = np.array([float(r["finished"]) for r in rows]); order = np.argsort(t, kind="stable")
    Ls = np.zeros((N, 3)); Lr = np.zeros((N, 3))
    for k, n in enumerate(order):
        rc = d["recs"][k]
        Ls[n] = st.sample_radiance(inst.sample, rc["wi"], rc["wo"])[0]
        Lr[n] = st.reference_radiance(inst.reference, rc["wi"], rc["wo"])[0]
    s = st.model.stray.floor / math.pi
    ref = ReferenceModel(settings["reference"])
    # nominal angles the bench used for the reference model: the row's own theta_i/theta_o (journal)
    fref = np.array([ref.f_r(r["theta_i"], r["theta_o"]) for r in rows])
    y_nf = (Ls + s) / (Lr + s) * fref
    y_nf_nostray = Ls / Lr * fref
    m2, res, G, S = A["m2"], A["res"], A["G"], A["S"]
    meas_y = m2.brdf  # aperture-corrected data; compare the raw too
    from gonio.fitting import load_dataset
    meas = load_dataset(Path(d["path"]))
    ds = A["ds"]
    cal = np.stack([ds[k].values for k in ("theta_i", "phi_i", "theta_o", "phi_o")], -1)
    wi_c, wo_c = dirs(np.radians(cal[:, 0]), np.radians(cal[:, 1])), dirs(np.radians(cal[:, 2]), np.radians(cal[:, 3]))
    names = list(res.space.names)
    xt = np.array(out["xt"])
    params = res.space.to_params(xt) if hasattr(res.space, "to_params") else None
    return dict(A=A, out=out, Ls=Ls, Lr=Lr, s=s, fref=fref, y_nf=y_nf, y_nf_nostray=y_nf_nostray, meas=meas, cal=cal,
                wi_c=wi_c, wo_c=wo_c, st=st, inst=inst, settings=settings, rows=rows)

if __name__ == "__main__" and len(sys.argv) == 3:
    R = recon(sys.argv[1], int(sys.argv[2]))
    meas = R["meas"]
    z = (meas.brdf - R["y_nf"]) / meas.brdf_std
    print("data - noise-free reconstruction, in brdf_std: mean", z.mean(0), "sd", z.std(0))
    print("rel diff median", np.median(np.abs(meas.brdf / R["y_nf"] - 1), 0))
    print(R["A"]["res"].space.names, type(R["A"]["res"].space))


def parts(sample, seed, brow):
    from gonio.sim.physics.errors import _cone, disk_rule, _small_rotation
    from gonio.fitting.likelihood.aperture import aperture_ratio
    R = recon(sample, seed)
    A, out = R["A"], R["out"]
    st, inst = R["st"], R["inst"]
    res, m2, G = A["res"], A["m2"], A["G"]
    d = pickle.load(open(f"{WORK}/rec-{sample}-{seed}.pkl", "rb"))
    rows = R["rows"]; N = len(rows)
    t = np.array([float(r["finished"]) for r in rows]); order = np.argsort(t, kind="stable")
    _, w = disk_rule()
    half = math.radians(st.model.aperture.source_half_deg)
    F = _small_rotation(st.wedge_deg)
    cs, cr = np.zeros(N), np.zeros(N)
    for k, n in enumerate(order):
        rc = d["recs"][k]
        di = _cone(rc["wi"], half)
        cr[n] = w @ np.maximum(di[:, 2], 0)
        cs[n] = w @ np.maximum((di @ F)[:, 2], 0)
    fs_t = R["Ls"] / cs[:, None]
    fr_t = R["Lr"] / cr[:, None]
    params = res.space.to_params(np.array(out["xt"]))
    y_ideal = aperture_mean(res.model, R["wi_c"], R["wo_c"], params, 0.5, 0.5)
    fref = R["fref"]
    y_nf, y_ns = R["y_nf"], R["y_nf_nostray"]
    # the fit model at the TRUE angles (face frame) vs the sim's own aperture mean there
    ta = A["e"] + R["cal"]
    wi_t, wo_t = dirs(np.radians(ta[:, 0]), np.radians(ta[:, 1])), dirs(np.radians(ta[:, 2]), np.radians(ta[:, 3]))
    y_true_fitrule = aperture_mean(res.model, wi_t, wo_t, params, 0.5, 0.5)
    cert = fs_t * (cs / cr)[:, None] * (1.0 / st.rho_factor - 1.0)
    refall = y_ns - fs_t
    c = m2.brdf / R["meas"].brdf
    use = m2.use
    def dx(v):
        return np.einsum("pnc,nc->p", np.where(use, G, 0), np.where(use, v / c, 0))
    P = {"angle(sim rule)": fs_t - y_ideal, "angle(fit rule)": y_true_fitrule - y_ideal,
         "rule sim-fit": fs_t - y_true_fitrule, "certificate": cert, "ref shape+cos": refall - cert,
         "stray": y_nf - y_ns, "noise": R["meas"].brdf - y_nf, "total": R["meas"].brdf - y_ideal}
    uc = np.array(brow["u_c"]); out["u_c"] = brow["u_c"]
    err = np.array(out["x"]) - np.array(out["xt"])
    res_ = {k: (dx(v) / uc).tolist() for k, v in P.items()}
    res_["err"] = (err / uc).tolist()
    res_["lin_angle"] = (np.array(out["dx_all"]) / uc).tolist()
    res_["seed"] = seed
    res_["names"] = out["names"]
    res_["u_c"] = out["u_c"]; res_["fractions"] = out.get("fractions")
    return res_

if __name__ == "__main__" and len(sys.argv) > 3:
    import glob
    rowsj = json.load(open(f"{WORK}/batch-{sys.argv[1]}-401500.json"))
    allp = []
    for r in rowsj:
        p = parts(sys.argv[1], r["seed"], r)
        p["fractions"] = r["fractions"]
        allp.append(p)
        print(r["seed"], {k: np.round(v[3:], 2).tolist() for k, v in p.items() if k not in ("seed", "names", "u_c", "fractions")}, flush=True)
    json.dump(allp, open(f"{WORK}/parts-{sys.argv[1]}.json", "w"))
