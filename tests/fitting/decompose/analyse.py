import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import pickle, sys, math, json
from pathlib import Path
import numpy as np
import budget_coverage as BC
from gonio.sim.physics.errors import _small_rotation
from gonio.bench.measure import calpoint as CP
from gonio.bench.plan import kinematics
from gonio.bench.dataset.budget import move_history
from gonio.fitting import load_dataset, fit, with_instrument_response
from gonio.cli.fit import open_budget
from gonio.fitting.uncertainty.budget import _loss_sensitivities, slope, angle_components
import gonio.models as gm

def angles(w):
    t, p = kinematics.angles_of(w)
    return t, p

def analyse(sample, seed, nmc=4000, verbose=True):
    d = pickle.load(open(f"{WORK}/rec-{sample}-{seed}.pkl", "rb"))
    recs, rows, cal = d["recs"], d["rows"], d["cal"]
    meas = load_dataset(Path(d["path"]))
    budget = open_budget(Path(d["path"]), meas)
    spec, options, shape, plan = BC.CAPTURE_SAMPLES[sample]
    model = gm.get("roughplastic", **options)
    res = fit(meas, model, rng=np.random.default_rng(seed))
    res, m2, b2 = with_instrument_response(meas, budget, res, lambda m: fit(m, model, rng=np.random.default_rng(seed)))
    names = list(res.space.names)
    truth = {"diffuse_reflectance[R]": 0.5, "diffuse_reflectance[G]": 0.35, "diffuse_reflectance[B]": 0.2, **shape}
    xt = np.array([truth[n] for n in names])
    use = m2.use
    J, drdy = _loss_sensitivities(res, m2)
    P = len(names)
    G = np.zeros((P,) + use.shape)
    G[:, use] = -np.linalg.pinv(J, rcond=1e-10) * drdy[None, :]
    S = slope(res.model, res.params, m2.wi, m2.wo)        # (N, C, 4) per degree
    # rows -> records
    t = np.array([float(r["finished"]) for r in rows])
    order = np.argsort(t, kind="stable")
    stage = np.array([[r[k] for k in ("yaw", "tilt", "azimuth", "lamp")] for r in rows], float)
    N = len(rows)
    true_ang = np.zeros((N, 4)); rep = np.zeros((N, 4)); moves = np.zeros((N, 4), int); ldir = np.zeros((N, 4))
    for k, n in enumerate(order):
        rc = recs[k]
        assert np.allclose(rc["deg"], stage[n], atol=1e-3), (rc["deg"], stage[n])
        F = _small_rotation(rc["wedge"])
        wi, wo = rc["wi"] @ F, rc["wo"] @ F
        ti, pi_ = angles(wi[None]); to, po = angles(wo[None])
        true_ang[n] = [ti[0], pi_[0], to[0], po[0]]
        for (i, mv, ld, tot, z) in rc["parts"]:
            rep[n, i] = tot - z + 0.5 * 0.02 * ld
            moves[n, i] = mv; ldir[n, i] = ld
    # kinematics.angles_of returns degrees? check
    cal_ang = np.stack([meas.attrs.get("x", None) or 0 for _ in range(1)]) if False else None
    import xarray as xr
    ds = xr.open_dataset(d["path"])
    cal_ang = np.stack([ds[k].values for k in ("theta_i", "phi_i", "theta_o", "phi_o")], -1)
    e = true_ang - cal_ang
    e[:, 1::2] = (e[:, 1::2] + 180) % 360 - 180
    labels, last = move_history(rows)
    p = CP._p(cal)
    Ji = CP._jacobian(stage, p, ["axis0", "axis1", "axis2", "axis3"])    # (N, 4, 4)
    e_rep = np.einsum("nak,nk->na", Ji, rep)
    e_rest = e - e_rep
    def dx(ef):
        dy = np.einsum("nca,na->nc", S, ef)
        return np.einsum("pnc,nc->p", np.where(use, G, 0.0), np.where(use, dy, 0.0))
    # budget side
    comps = angle_components(res, m2, b2.angles)
    var = {c.name: np.diag(c.covariance(G, use)) for c in comps}
    # MC of the repeatability with the simulator's move labels
    rng = np.random.default_rng(1)
    sd = 0.01
    mc = []
    for _ in range(nmc):
        r = np.zeros((N, 4))
        for i in range(4):
            u, inv = np.unique(moves[:, i], return_inverse=True)
            r[:, i] = sd * rng.standard_normal(len(u))[inv] * (moves[:, i] > 0)
        mc.append(dx(np.einsum("nak,nk->na", Ji, r)))
    mc = np.array(mc)
    # same MC with the budget's labels
    mcb = []
    for _ in range(nmc):
        r = np.zeros((N, 4))
        for i in range(4):
            u, inv = np.unique(labels[:, i], return_inverse=True)
            r[:, i] = sd * rng.standard_normal(len(u))[inv]
        mcb.append(dx(np.einsum("nak,nk->na", Ji, r)))
    mcb = np.array(mcb)
    budget_rep = sum(v for k, v in var.items() if k.startswith("angle_repeatability"))
    out = {"names": names, "x": np.asarray(res.x).tolist(), "xt": xt.tolist(),
           "dx_rep": dx(e_rep).tolist(), "dx_rest": dx(e_rest).tolist(), "dx_all": dx(e).tolist(),
           "var_budget_rep": budget_rep.tolist(), "var_mc_sim": mc.var(0).tolist(), "var_mc_lab": mcb.var(0).tolist(),
           "var_budget": {k: v.tolist() for k, v in var.items()},
           "labels_equal": bool(all(len(np.unique(np.stack([labels[:, i], moves[:, i]], 1), axis=0)) == len(np.unique(labels[:, i])) == len(np.unique(moves[:, i])) for i in range(4))),
           "n_moves_sim": [len(np.unique(moves[:, i])) for i in range(4)], "n_labels": [len(np.unique(labels[:, i])) for i in range(4)],
           "e_rms": np.sqrt((e ** 2).mean(0)).tolist(), "e_rest_rms": np.sqrt((e_rest ** 2).mean(0)).tolist(),
           "e_rest_mean": e_rest.mean(0).tolist(), "rep_rms": np.sqrt((rep**2).mean(0)).tolist()}
    if verbose:
        for k, v in out.items():
            print(k, v)
    return out, dict(e=e, e_rest=e_rest, e_rep=e_rep, rep=rep, moves=moves, labels=labels, stage=stage, G=G, S=S, Ji=Ji, res=res, m2=m2, b2=b2, cal=cal, ds=ds, rows=rows, ldir=ldir, last=last)

if __name__ == "__main__":
    analyse(sys.argv[1], int(sys.argv[2]))
