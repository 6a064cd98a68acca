import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import json, sys, numpy as np
for sample in ("glossy", "roughplastic"):
    try:
        rows = json.load(open(f"{WORK}/batch-{sample}-401500.json"))
    except Exception:
        continue
    names = rows[0]["names"]
    print(sample, len(rows))
    z = {}
    for r in rows:
        uc = np.array(r["u_c"]); vb = r["var_budget"]
        shared = np.array(vb["angle_shared"]); rep = np.array(r["var_budget_rep"])
        err = np.array(r["x"]) - np.array(r["xt"])
        ang = np.array(r["dx_all"])
        other_var = uc ** 2 - shared - rep
        for k, v in (("total", err / uc), ("rep", np.array(r["dx_rep"]) / np.sqrt(rep)),
                     ("shared", np.array(r["dx_rest"]) / np.sqrt(shared)),
                     ("nonangle", (err - ang) / np.sqrt(other_var)),
                     ("mc/budget rep", np.array(r["var_mc_sim"]) / rep)):
            z.setdefault(k, []).append(v)
        z.setdefault("frac", []).append([shared / uc**2, rep / uc**2])
    for k, v in z.items():
        v = np.array(v)
        if k == "frac":
            print("  budget fraction shared, rep:", np.round(v.mean(0), 3).tolist())
        elif k.startswith("mc"):
            print(f"  {k:14s} mean", np.round(v.mean(0), 3).tolist())
        else:
            print(f"  {k:14s} rms", np.round(np.sqrt((v ** 2).mean(0)), 2).tolist(), "mean", np.round(v.mean(0), 2).tolist())
