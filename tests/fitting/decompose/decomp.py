"""Decompose one capture session's angle errors: truth (simulator) vs the calibrated angles."""
import os as _os
import sys as _sys
from pathlib import Path as _P
_HERE = _P(__file__).resolve().parent
WORK = _P(_os.environ.get("GONIO_DECOMPOSE_DIR", "/tmp/gonio-decompose"))
WORK.mkdir(parents=True, exist_ok=True)
_sys.path[:0] = [str(_HERE), str(_HERE.parent)]

import json, math, shutil, sys, pickle
from pathlib import Path
import numpy as np

import budget_coverage as BC
import gonio.sim.instrument as SI
from gonio.sim.physics.errors import _small_rotation

REC = []
_orig = SI.Instrument.geometry

def geometry(self, pose=None):
    g = _orig(self, pose)
    if self._errors_on:
        pose_ = self.pose_microsteps() if pose is None else pose
        st = self.error_state
        parts = []
        for n, a in zip(self.axis_names, self.axes):
            i = SI._AXIS_NAMES.index(n)
            tot = st.axis_error_deg(i, a.moves, a.last_dir)
            parts.append((i, a.moves, a.last_dir, tot, st.zero_deg[i]))
        REC.append({"pose": tuple(pose_), "wi": np.array(g["wi"]), "wo": np.array(g["wo"]), "parts": parts,
                    "deg": tuple(p * 360.0 / a.cycle_dist for p, a in zip(pose_, self.axes)),
                    "wedge": st.wedge_deg})
    return g

SI.Instrument.geometry = geometry


def run(seed, sample):
    from gonio.bench.settings import default_settings
    from gonio.bench.calibrate import calibrate, merge_calibration
    from gonio.bench.dataset.export import export
    from gonio.cli.fit import fit_dataset, open_budget
    from gonio.cli.capture import capture_sim
    from gonio.bench.session import integrity as _integrity
    from gonio.fitting import load_dataset
    settings = default_settings()
    settings["errors"] = {"preset": "typical"}
    cal = calibrate(settings, seed=seed)
    settings = merge_calibration(settings, cal)
    spec, options, shape, plan = BC.CAPTURE_SAMPLES[sample]
    folder = Path(f"{WORK}/s-{sample}-{seed}")
    shutil.rmtree(folder, ignore_errors=True)
    REC.clear()
    capture_sim(folder, sample=spec, plan=plan, seed=seed, settings=settings, progress=False)
    recs = list(REC)
    path = export(folder)
    data, doc, why = _integrity.load_session(folder)
    with _integrity.open_journal(folder, data, doc, why, write=False) as j:
        rows = j.points()
    return cal, settings, recs, rows, path

if __name__ == "__main__":
    seed, sample = int(sys.argv[1]), sys.argv[2]
    cal, settings, recs, rows, path = run(seed, sample)
    pickle.dump({"cal": cal, "recs": recs, "rows": rows, "path": str(path)}, open(f"{WORK}/rec-{sample}-{seed}.pkl", "wb"))
    print(len(recs), len(rows))
