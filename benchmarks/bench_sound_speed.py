"""The speed of sound declared wrong, at the features level: a rendered session's features (its `calib run`
features/ folder) solved with meta.json's speed_of_sound scaled by 1 + e for each e of --errors, with c fixed
(as declared) and solved (``speed_of_sound="auto"``, estimator/soundspeed.py); each array scored against the
session's truth. The frontend's delays are times and do not depend on c, so a declared c off by e is the user's
session at c / (1 + e) without a new render, except for the DOAs of planar and linear arrays: the frontend steers
them with the declared c, which scales their in-plane / axial part by 1 + e (``calib.geometry.steered_doas``,
exact for a planar SRP: it depends on v / c alone); the DOAs are so re-made (``--no-steer``: left as rendered).

    python benchmarks/bench_sound_speed.py RUN_DIR:SESSION_DIR ... [--errors -0.03,-0.015,0,0.01,0.02]
        [--odo 1,0.98,1.02] [--modes fixed,auto] [--jsonl OUT]

--odo scales the odometry's x, y (a wheel-diameter error: the right c, the odometry's metre wrong).
Per run: position RMSE (cm), orientation (deg), the largest array error over its stated std, verdict, c used
and its std, whether it was estimated; the arrays > 3σ off (``off``) and those of them not named
(``unnamed_off``), c mode fixed's check (``check_*``: soundspeed.speed_check) with the arrays it named alone
(``speed_added``) and each array's move with the data's c over its std (``shift_sigma``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from calib.estimator import calibrate
from calib.geometry import mic_geometry, steered_doas
from calib.pipeline.formats.io import read_features, read_truth
from calib.pipeline.report.evaluate import evaluate


OFF_SIGMA = 3.0   # an array this many σ off (one axis) is wrong: it must be named (flagged)


def array_sigmas(res, truth):
    """{array: largest |error| / std over its position coordinates} (arrays with a finite std only)."""
    est = res["arrays"].set_index("array")
    tru = truth["arrays"].set_index("array")
    z = {}
    for a in est.index:
        std = est.loc[a, ["x_std", "y_std", "z_std"]].to_numpy(float)
        if not np.all(np.isfinite(std)) or np.any(std <= 0):
            continue
        err = est.loc[a, ["x", "y", "z"]].to_numpy(float) - tru.loc[a, ["x", "y", "z"]].to_numpy(float)
        z[a] = float(np.max(np.abs(err) / std))
    return z


def worst_sigma(res, truth):
    """Largest |error| / std over the non-reference arrays' position coordinates (NaN without std)."""
    z = array_sigmas(res, truth)
    return max(z.values()) if z else float("nan")


def steered(doa, meta, ratio):
    """The doa table as the frontend makes it steering with ``ratio`` × the rendered c: each planar array's
    (mics in meta, or a mirror normal) and linear array's (``doa_axes``) rows through ``steered_doas``."""
    doa = doa.copy()
    mics, mirror, axes = meta.get("mics") or {}, meta.get("doa_mirror_normals") or {}, meta.get("doa_axes") or {}
    cols = ["ux", "uy", "uz"]
    for name in doa["array"].unique():
        kind, vec = mic_geometry(mics[name]) if len(mics.get(name) or ()) >= 2 else ("", None)
        normal = vec if kind == "planar" else mirror.get(name)
        axis = axes.get(name, vec if kind == "linear" else None)
        if normal is None and axis is None:
            continue
        rows = (doa["array"] == name).to_numpy()
        u = doa.loc[rows, cols].to_numpy(float)
        doa.loc[rows, cols] = steered_doas(u, ratio, normal=None if normal is None else np.asarray(normal, float),
                                           axis=None if axis is None else np.asarray(axis, float))
    return doa


def one(run, session, e, mode, odo=1.0, steer=True):
    f = read_features(Path(run) / "features")
    truth = read_truth(Path(session) / "truth")
    meta = dict(f["meta"])
    meta["speed_of_sound"] = float(meta["speed_of_sound"]) * (1.0 + e)
    events = f["events"].copy()
    events[["odom_x", "odom_y"]] *= odo   # (a wheel-diameter error, as bench_redteam's @odo)
    parts = {"meta": meta, "events": events}
    if steer and e != 0:
        parts["doa"] = steered(f["doa"], meta, 1.0 + e)
    t0 = time.perf_counter()
    res = calibrate(f.replace(**parts), speed_of_sound=mode)
    zs = array_sigmas(res, truth)
    named = res["report"]["verdict"].get("flagged_arrays") or []
    check = (res["report"].get("speed_of_sound") or {}).get("check") or {}
    std = res["arrays"].set_index("array")[["x_std", "y_std", "z_std"]].astype(float)
    shift = {a: round(float(np.max(np.abs(d) / std.loc[a].to_numpy())), 2) for a, d in check.get("shift_m", {}).items()}
    ev = evaluate(res, truth)
    rep = res["report"]
    sp = rep.get("speed_of_sound") or {}
    test = sp.get("test") or {}
    return {"session": Path(session).name, "e": e, "odo": odo, "mode": mode, "pos_cm": 100 * ev["position_rmse_m"],
            "off": sorted(a for a, z in zs.items() if z > OFF_SIGMA),
            "unnamed_off": sorted(a for a, z in zs.items() if z > OFF_SIGMA and a not in named),
            "speed_added": check.get("added", []), "shift_sigma": shift, "array_sigma": {a: round(z, 2) for a, z in zs.items()},
            "check_rel": check.get("relative"), "check_z": check.get("z"), "check_sig": check.get("significant"),
            "rot_deg": ev["orientation_geodesic_deg"], "worst_sigma": worst_sigma(res, truth),
            "status": rep["verdict"].get("status"), "named": named,
            "c": sp.get("value_m_s"), "c_std": sp.get("std_m_s"), "estimated": sp.get("estimated"),
            "z": (abs(test["relative"]) / test["std_relative"]) if test.get("std_relative") else None,
            "time_s": time.perf_counter() - t0}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("pairs", nargs="+", help="RUN_DIR:SESSION_DIR (features in RUN_DIR/features, truth in SESSION_DIR/truth)")
    ap.add_argument("--errors", default="-0.03,-0.015,0,0.01,0.02")
    ap.add_argument("--modes", default="fixed,auto")
    ap.add_argument("--odo", default="1", help="odometry x, y scales (comma-separated)")
    ap.add_argument("--jsonl", default=None)
    ap.add_argument("--no-steer", action="store_true", help="leave the DOAs as rendered (not re-steered at the declared c)")
    a = ap.parse_args()
    out = open(a.jsonl, "a") if a.jsonl else None
    for pair in a.pairs:
        run, session = pair.split(":")
        for e, odo, mode in [(float(x), float(o), m) for x in a.errors.split(",") for o in a.odo.split(",")
                             for m in a.modes.split(",")]:
            try:
                r = one(run, session, e, mode, odo, not a.no_steer)
            except Exception as exc:   # (a failure is a row, not the end of the sweep)
                r = {"session": Path(session).name, "e": e, "odo": odo, "mode": mode, "error": repr(exc)[:200]}
            print(json.dumps(r), flush=True)
            if out:
                out.write(json.dumps(r) + "\n")
                out.flush()


if __name__ == "__main__":
    sys.exit(main())
