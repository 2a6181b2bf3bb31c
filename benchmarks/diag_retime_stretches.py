"""Each array's searched and predicted Doppler stretches against the rendered truth (a source moving during its sweep).

    python benchmarks/diag_retime_stretches.py SESSION [SESSION ...] [--csv out.csv]

SESSION: a rendered session folder (`calib simulate`, truth/manifest.json). The first pass of the frontend runs
(``extract_features``), then the re-timing pass's first solve (pipeline/retime.py ``first_solve``) and its
predicted stretches (``estimator.motion.predicted_stretches``). Per array, over its events, in bank steps: how
many searched stretches (the frontend's own Doppler bank search) are half a step or more from the truth's ε =
ṙ(t*)/c + drift (ṙ by central differences of the true trajectory), how many predicted ones are a step or more
off it, how many predicted and searched ones are half a step apart (what a consistency test would see), the
first solve's position error (cm, against truth/arrays.csv as the state gives it, no alignment: deploy 507's
metres with stretches right are its frame, not its geometry) and whether it called the array unreliable. deploy
505–513: searched 13–30 of 30 half a step off for most arrays (the reflections' Doppler), predicted 0–6 of 30 a
step off except 505 A5 (18 of 30) and 507 A5 (19, a diverged first solve).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

RANGE_STEP = 1e-3   # s: the range rate by central differences of the true trajectory


def session_rows(folder):
    """One row per array of the rendered session ``folder`` (module doc)."""
    from calib.estimator.motion import predicted_stretches
    from calib.estimator.outputs import to_tables
    from calib.frontend import extract_features
    from calib.pipeline.formats.io import read_truth
    from calib.pipeline.formats.session import read_session
    from calib.pipeline.report.evaluate import array_errors
    from calib.pipeline.retime import FIRST_SOLVE_OUTLIERS, first_solve
    from calib.pipeline.simulate.scenario import validate_scenario

    session = read_session(folder)
    feats, diag = extract_features(session)
    if diag.get("_retime") is None:
        return []
    sol, why = first_solve(session, feats, FIRST_SOLVE_OUTLIERS)
    if sol is None:
        print(f"{folder.name}: {why}", file=sys.stderr)
        return []
    p, st = sol["problem"], sol["state"]
    ts = feats["meta"].get("stretch_time_s") or 0.0
    eps = predicted_stretches(p, st, feats["events"], ts)
    err = array_errors(to_tables(p, st)[0], read_truth(folder / "truth")["arrays"])
    pos_cm = dict(zip(err["array"], 100 * err["position_m"]))
    sc = validate_scenario(json.loads((folder / "truth" / "manifest.json").read_text())["scenario"])
    c, traj = sc["speed_of_sound"], sc["trajectory"]
    ev_ids = session["events"]["event"].to_numpy(int)
    col = {int(e): k for k, e in enumerate(p.events)}
    truth = {a["name"]: a for a in sc["arrays"]}
    rows = []
    for i, name in enumerate(map(str, p.names)):
        k = diag["_retime"]["arrays"][name]
        grid, ev_idx = k["ctx"]["bank"][1], np.asarray(k["ctx"]["ev_idx"])
        step = grid[1] - grid[0]
        pred = np.array([eps[i, col[int(e)]] if int(e) in col else np.nan for e in ev_ids])[ev_idx]
        x, t = np.asarray(truth[name]["position"], float), np.asarray(sc["t_emit"], float)[ev_idx] + ts
        rate = (np.linalg.norm(traj(t + RANGE_STEP) - x, axis=1)
                - np.linalg.norm(traj(t - RANGE_STEP) - x, axis=1)) / (2 * RANGE_STEP)
        true = rate / c + truth[name]["drift"]
        searched = np.asarray(k["loc"]["stretch"], float)
        f = np.isfinite(pred)
        rows.append({"session": folder.name, "array": name, "events": int(f.sum()),
                     "first solve error, unaligned (cm)": pos_cm.get(name, 0.0),
                     "unreliable": name in set(map(str, sol["unreliable_arrays"])),
                     "searched off truth >= 0.5 step": int(np.sum(np.abs(searched - true)[f] >= 0.5 * step)),
                     "predicted off truth >= 1 step": int(np.sum(np.abs(pred - true)[f] >= step)),
                     "predicted vs searched >= 0.5 step": int(np.sum(np.abs(pred - searched)[f] >= 0.5 * step))})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--csv", type=Path, help="write the rows here")
    args = ap.parse_args(argv)
    df = pd.DataFrame([r for f in args.sessions for r in session_rows(f)])
    if args.csv:
        df.to_csv(args.csv, index=False)
    print(df.to_string(index=False, float_format=lambda x: f"{x:.1f}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
