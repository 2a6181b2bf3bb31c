"""Every arrival the frontend times against the simulator's direct path (issues 27/28: late picks in line of sight).

    python benchmarks/diag_los_arrivals.py SESSION [SESSION ...] [--csv out.csv]

SESSION: a rendered session folder (`calib simulate`, with truth/manifest.json and truth/los.csv). The features
are computed as `calib features` does (re-timing pass included) and each (array, event) arrival (diagnostics, on
its array's clock) is compared with the truth's

    a_ij = L_i(t_emit[j] + |s_j - x_i| / c) + β δ_i (+ β ṙ_ij(t*) / c for a source moving during its sweep)

(the sweep start's direct path at the array origin on its clock, `scenario.arrival_times`, plus the drift bias
and the moving source's shift the estimator models; meta ``chirp_drift_bias`` and ``stretch_time_s``). On a
clean lab session the errors are within ±1.3 µs. Arrays extracted at a measured rate (a wrong WAV header) are
left out (their local times count samples at another rate). Per preset, over the arrivals in line of sight
(truth/los.csv ``los`` = 1): how many are more than 50 / 100 / 300 µs late or early, how many of those carry a
timing doubt, and the RMS of the errors about each array's median (a constant per array is a clock offset to
the estimator), clipped at ±300 µs.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

DOUBTS = "weak_direct|early_onset|low_snr|mic_spread|track|redetected|occluded|nlos"
RANGE_STEP = 1e-3   # s: the range rate by central differences of the true trajectory


def truth_arrivals(folder, meta):
    """{array: (K,) the truth's arrival of each event on the array's clock (module doc)}."""
    from calib.pipeline.simulate.scenario import arrival_times, validate_scenario

    sc = json.loads((folder / "truth" / "manifest.json").read_text())["scenario"]
    start = arrival_times(sc)
    beta, c = meta["chirp_drift_bias"], sc["speed_of_sound"]
    traj = validate_scenario(sc)["trajectory"] if sc.get("trajectory") else None
    t = np.asarray(sc["t_emit"], float) + (meta.get("stretch_time_s") or 0.0)
    out = {}
    for i, a in enumerate(sc["arrays"]):
        arr = start[i] + beta * a["drift"]
        if traj is not None:
            x = np.asarray(a["position"], float)
            rate = (np.linalg.norm(traj(t + RANGE_STEP) - x, axis=1)
                    - np.linalg.norm(traj(t - RANGE_STEP) - x, axis=1)) / (2 * RANGE_STEP)
            arr = arr + beta * rate / c
        out[a["name"]] = arr
    return out


def session_table(folder):
    """One row per (array, event): error (µs), flag, late_s, and the truth's los.csv columns."""
    from calib.pipeline.features import session_features

    feats, diag = session_features(folder)
    meta = feats["meta"]
    truth = truth_arrivals(folder, meta)
    skip = set(diag.get("header_rates") or {})
    rows = [{"session": folder.name, "array": name, "event": int(r["event"]),
             "err_us": 1e6 * (r["time"] - truth[name][int(r["event"])]), "flag": r.get("flag") or ""}
            for name, ad in diag["arrays"].items() if name not in skip for r in ad["arrivals"]]
    los = pd.read_csv(folder / "truth" / "los.csv", dtype={"array": str})
    return pd.DataFrame(rows).merge(los, on=["event", "array"], how="left")


def summary(df):
    """Per preset, the line-of-sight arrivals' error counts (module doc)."""
    d = df[df["los"] == 1].copy()
    d["preset"] = d["session"].str.rsplit("_", n=1).str[0]
    d["dev"] = d["err_us"] - d.groupby(["session", "array"])["err_us"].transform("median")
    doubt = d["flag"].str.contains(DOUBTS)

    def one(g):
        e = g["err_us"]
        big = e.abs() > 50
        return pd.Series({"arrivals": len(g), **{f"late>{k}": int((e > k).sum()) for k in (50, 100, 300)},
                          **{f"early>{k}": int((e < -k).sum()) for k in (50, 100, 300)},
                          ">50 doubted": int((big & doubt[g.index]).sum()),
                          "rms about array median (µs)": float(np.sqrt(np.mean(np.clip(g["dev"], -300, 300) ** 2)))})
    return d.groupby("preset").apply(one)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--csv", type=Path, help="write every arrival's row here")
    args = ap.parse_args(argv)
    df = pd.concat([session_table(f) for f in args.sessions], ignore_index=True)
    if args.csv:
        df.to_csv(args.csv, index=False)
    print(summary(df).to_string(float_format=lambda x: f"{x:.2f}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
