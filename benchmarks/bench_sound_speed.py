"""The speed of sound declared wrong, at the features level: a rendered session's features (its `calib run`
features/ folder) solved with meta.json's speed_of_sound scaled by 1 + e for each e of --errors, with c fixed
(as declared) and solved (``speed_of_sound="auto"``, estimator/soundspeed.py); each array scored against the
session's truth. Features do not depend on c at first order (the frontend's delays are times), so a declared
c off by e is the user's session at c / (1 + e) without a new render.

    python benchmarks/bench_sound_speed.py RUN_DIR:SESSION_DIR ... [--errors -0.03,-0.015,0,0.01,0.02]
        [--modes fixed,auto] [--jsonl OUT]

Per run: position RMSE (cm), orientation (deg), the largest array error over its stated std, verdict, c used
and its std, whether it was estimated.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from calib.estimator import calibrate
from calib.pipeline.formats.io import read_features, read_truth
from calib.pipeline.report.evaluate import evaluate


def worst_sigma(res, truth):
    """Largest |error| / std over the non-reference arrays' position coordinates (NaN without std)."""
    est = res["arrays"].set_index("array")
    tru = truth["arrays"].set_index("array")
    z = []
    for a in est.index:
        std = est.loc[a, ["x_std", "y_std", "z_std"]].to_numpy(float)
        if not np.all(np.isfinite(std)) or np.any(std <= 0):
            continue
        err = est.loc[a, ["x", "y", "z"]].to_numpy(float) - tru.loc[a, ["x", "y", "z"]].to_numpy(float)
        z.append(float(np.max(np.abs(err) / std)))
    return max(z) if z else float("nan")


def one(run, session, e, mode):
    f = read_features(Path(run) / "features")
    truth = read_truth(Path(session) / "truth")
    meta = dict(f["meta"])
    meta["speed_of_sound"] = float(meta["speed_of_sound"]) * (1.0 + e)
    t0 = time.perf_counter()
    res = calibrate(f.replace(meta=meta), speed_of_sound=mode)
    ev = evaluate(res, truth)
    rep = res["report"]
    sp = rep.get("speed_of_sound") or {}
    test = sp.get("test") or {}
    return {"session": Path(session).name, "e": e, "mode": mode, "pos_cm": 100 * ev["position_rmse_m"],
            "rot_deg": ev["orientation_geodesic_deg"], "worst_sigma": worst_sigma(res, truth),
            "status": rep["verdict"].get("status"), "named": rep["verdict"].get("flagged_arrays"),
            "c": sp.get("value_m_s"), "c_std": sp.get("std_m_s"), "estimated": sp.get("estimated"),
            "z": (abs(test["relative"]) / test["std_relative"]) if test.get("std_relative") else None,
            "time_s": time.perf_counter() - t0}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("pairs", nargs="+", help="RUN_DIR:SESSION_DIR (features in RUN_DIR/features, truth in SESSION_DIR/truth)")
    ap.add_argument("--errors", default="-0.03,-0.015,0,0.01,0.02")
    ap.add_argument("--modes", default="fixed,auto")
    ap.add_argument("--jsonl", default=None)
    a = ap.parse_args()
    out = open(a.jsonl, "a") if a.jsonl else None
    for pair in a.pairs:
        run, session = pair.split(":")
        for e in [float(x) for x in a.errors.split(",")]:
            for mode in a.modes.split(","):
                try:
                    r = one(run, session, e, mode)
                except Exception as exc:   # (a failure is a row, not the end of the sweep)
                    r = {"session": Path(session).name, "e": e, "mode": mode, "error": repr(exc)[:200]}
                print(json.dumps(r), flush=True)
                if out:
                    out.write(json.dumps(r) + "\n")
                    out.flush()


if __name__ == "__main__":
    sys.exit(main())
