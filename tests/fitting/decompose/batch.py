import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import sys, json, pickle
import decomp
from analyse import analyse
import numpy as np
from gonio.fitting import fit_document
sample, first, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
outf = f"{WORK}/batch-{sample}-{first}.json"
rows = []
for seed in range(first, first + n):
    cal, settings, recs, jrows, path = decomp.run(seed, sample)
    pickle.dump({"cal": cal, "recs": recs, "rows": jrows, "path": str(path)}, open(f"{WORK}/rec-{sample}-{seed}.pkl", "wb"))
    out, A = analyse(sample, seed, nmc=300, verbose=False)
    doc = fit_document(A["res"], A["m2"], seed=seed, budget=A["b2"])
    u = doc["uncertainty"]["parameters"]
    out["u_c"] = [u[k]["u_combined"] for k in out["names"]]
    out["u_stat"] = [u[k]["u_stat"] for k in out["names"]]
    out["fractions"] = [u[k]["budget"] for k in out["names"]]
    out["seed"] = seed
    rows.append(out)
    json.dump(rows, open(outf, "w"))
    print(seed, flush=True)
