"""The alignment alone (gonio calibrate's cross-scans) against the simulator's drawn truth (issue 15).

    .venv/bin/python tests/fitting/decompose/calstudy.py FIRST_SEED END_SEED OUT.json

gonio/bench/calibrate.align on the typical instrument per seed (about 5 s each): estimates, stated u
and truth of the yaw and tilt zeros, the holder tilt (azimuth counter's frame) and the three
backlashes, written after every seed. Summarised in budget_coverage.py's docstring (seeds
402000-402076: lamp backlash mean z -0.12 +- 0.12, no bias).
"""
import sys, json, math, time
import numpy as np
from gonio.bench.measure import alignment as al
from gonio.bench import calibrate as C
from gonio.bench.settings import default_settings

def one(seed, preset="typical"):
    s = default_settings(); s["errors"] = {"preset": preset}
    bench, specs = C._sim_bench(s, seed)
    a = C.align(bench, s, 0.02, float(specs["repeat_deg"]))
    st = bench.inst.error_state
    n = al._rz(math.radians(st.zero_deg[2])) @ al.holder_rotation(*st.tilt_deg)[:, 2]
    truth = {"yaw_zero_deg": st.zero_deg[0] - 0.5*st.zero_deg[3], "tilt_zero_deg": st.zero_deg[1],
             "holder_tilt_x_deg": math.degrees(math.atan2(-n[1], n[2])), "holder_tilt_y_deg": math.degrees(math.asin(n[0])),
             **{f"backlash_{k}_deg": st.model.stages.backlash_deg for k in ("yaw", "tilt", "lamp")}}
    return {"seed": seed, "truth": truth, "est": {k: a[k] for k in truth}, "u": {k: a["u_"+k] for k in truth},
            "peaks": a["peaks"], "chi2": a["chi2"], "zero_deg": list(st.zero_deg), "tilt_deg": list(st.tilt_deg)}

if __name__ == "__main__":
    lo, hi, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    rows = []
    for seed in range(lo, hi):
        t = time.time()
        rows.append(one(seed))
        r = rows[-1]
        print(seed, round(time.time()-t,1), " ".join(f"{k[:12]}={(r['est'][k]-r['truth'][k])/r['u'][k]:+.2f}" for k in r["truth"]), flush=True)
        json.dump(rows, open(out, "w"))
