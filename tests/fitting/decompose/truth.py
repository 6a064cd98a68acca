import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]
import sys, numpy as np
from analyse import analyse
from gonio.bench.measure import calpoint as CP
import gonio.sim
sample, seed = sys.argv[1], int(sys.argv[2])
out, A = analyse(sample, seed, nmc=200, verbose=False)
cal = A["cal"]; stage = A["stage"]
st = gonio.sim.error_model({"preset": "typical"}).draw(seed, 0.005)
print("zero", st.zero_deg, "tilt", st.tilt_deg, "wedge", st.wedge_deg)
a = cal["alignment"]
print("est", [a[k] for k in ("yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg", "holder_tilt_y_deg")], "u", [a.get("u_"+k) for k in ("yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg", "holder_tilt_y_deg")])
print("backlash est", [a.get(f"backlash_{n}_deg") for n in ("yaw","tilt","lamp")], [a.get(f"u_backlash_{n}_deg") for n in ("yaw","tilt","lamp")])
p_true = np.array([st.zero_deg[0], st.zero_deg[1], st.tilt_deg[0], st.tilt_deg[1]])
ax = A["rep"] + np.array([0, 0, st.zero_deg[2], st.zero_deg[3]]) - 0.5 * 0.02 * A["ldir"]
model_true = CP._angles(stage, p_true, ax, st.wedge_deg)
ds = A["ds"]
cal_ang = np.stack([ds[k].values for k in ("theta_i", "phi_i", "theta_o", "phi_o")], -1)
true_ang = cal_ang + A["e"]
d = model_true - true_ang
d[:, 1::2] = (d[:, 1::2] + 180) % 360 - 180
print("kinematic model vs sim truth, max |d| theta_i phi_i theta_o phi_o:", np.abs(d).max(0))
print("ldir vs budget last dir agree:", np.mean(A["ldir"] == A["last"], 0))
