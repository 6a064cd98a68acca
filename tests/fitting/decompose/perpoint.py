import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import sys, numpy as np
from recon import recon
from gonio.fitting.likelihood.aperture import aperture_mean
from gonio.core.geometry import directions as dirs
import json
sample, seed = sys.argv[1], int(sys.argv[2])
R = recon(sample, seed)
A = R["A"]; res = A["res"]; S = A["S"]; G = A["G"]; m2 = A["m2"]
xt = np.array(R["out"]["xt"]); params = res.space.to_params(xt)
cal = R["cal"]; ta = cal + A["e"]
def am(a):
    return aperture_mean(res.model, dirs(np.radians(a[:, 0]), np.radians(a[:, 1])), dirs(np.radians(a[:, 2]), np.radians(a[:, 3])), params, 0.5, 0.5)
def pm(a):
    return res.model.eval(dirs(np.radians(a[:, 0]), np.radians(a[:, 1])), dirs(np.radians(a[:, 2]), np.radians(a[:, 3])), params)
exact = am(ta) - am(cal)
exact_pt = pm(ta) - pm(cal)
lin = np.einsum("nca,na->nc", S, A["e"])
c = m2.brdf / R["meas"].brdf
ga = np.where(m2.use, G[3], 0) / c
uc = np.array(json.load(open(f"{WORK}/batch-{sample}-401500.json"))[seed - 401500]["u_c"])[3]
ex_a = (ga * exact).sum(1) / uc; li_a = (ga * lin).sum(1) / uc; ep = (ga * exact_pt).sum(1) / uc
idx = np.argsort(-np.abs(ex_a - li_a))[:10]
np.set_printoptions(suppress=True, linewidth=200, precision=4)
print("alpha z: exact", ex_a.sum(), "exact point-model", ep.sum(), "linear", li_a.sum())
for n in idx:
    print(n, "cal", cal[n].round(3), "e", A["e"][n].round(4), "dz exact %.3f pt %.3f lin %.3f" % (ex_a[n], ep[n], li_a[n]), "f", am(cal[n:n+1])[0, 1].round(3))
