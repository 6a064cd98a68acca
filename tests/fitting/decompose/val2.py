import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import sys, json, numpy as np
from analyse import analyse
from gonio.fitting.uncertainty.budget import second_order
sample = sys.argv[1]
parts = {p["seed"]: p for p in json.load(open(f"{WORK}/parts-{sample}.json"))}
rows = []
for seed in sorted(parts)[: int(sys.argv[2])]:
    out, A = analyse(sample, seed, nmc=2, verbose=False)
    p = parts[seed]; uc = np.array(p["u_c"])
    b, cov, H = second_order(A["res"], A["m2"], A["b2"].angles["shared"], A["G"], A["m2"].use)
    real = np.array(p["angle(fit rule)"]) - np.array(p["lin_angle"])
    sd = np.sqrt(np.clip(np.diag(cov) - b ** 2, 0, None))
    rows.append((real, b / uc, sd / uc))
    print(seed, "realised exact-lin", np.round(real[3:], 2), "predicted mean", np.round(b[3:] / uc[3:], 2), "sd", np.round(sd[3:] / uc[3:], 2), flush=True)
r = np.array(rows)
print("mean realised", np.round(r[:, 0].mean(0), 3), "mean predicted", np.round(r[:, 1].mean(0), 3), "rms realised", np.round(np.sqrt((r[:, 0]**2).mean(0)), 3), "rms predicted", np.round(np.sqrt((r[:, 1]**2 + r[:, 2]**2).mean(0)), 3))
