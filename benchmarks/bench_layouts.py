"""Real layouts in (issue 30): a simulated session rewritten as each board's raw recording, as one file per
mic, and with its robot log as ROS 1 / ROS 2 bags (speaker lever arm, playback latency); `calib run` on each
(a subprocess, the user's path) against `calib run` on the clean session, errors vs truth.

    python benchmarks/bench_layouts.py                  # seeds 0 1 2, lab3, 14 stops
    python benchmarks/bench_layouts.py --seeds 0 --boards respeaker-usb-4mic

Prints one row per (layout, seed): array position RMSE (cm), orientation (deg), offsets (µs), sources (cm),
clean and converted, and the ratio converted / clean of each; then the acceptance (every ratio ≤ 1.10) and
the same bag session with the lever arm not modelled (session.toml without [robot] speaker_offset).
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from calib.pipeline.formats.boards import BOARDS
from calib.pipeline.simulate import layouts
from calib.pipeline.simulate.roomsim import make_scenario, simulate

METRICS = {"loc_cm": ("position_rmse_m", 100), "geo_deg": ("orientation_geodesic_deg", 1),
           "offset_us": ("offset_rmse_s", 1e6), "src_cm": ("source_rmse_m", 100)}
TOLERANCE = 1.10  # the "as accurately as the clean equivalent (within 10 %)"
LEVER_ARM = (0.15, 0.10, 0.20)  # m, robot frame: 18 cm in the plane (rotates with the heading), 20 cm up
LATENCY = 0.02  # s


def calib(*args):
    p = subprocess.run(["calib", *map(str, args)], capture_output=True, text=True)
    if p.returncode not in (0, 3):
        sys.exit(f"calib {' '.join(map(str, args))}: exit {p.returncode}\n{p.stderr}")
    return p


def errors(rec, out):
    """Errors vs truth of `calib run REC` (None: not defined, e.g. a linear array's roll about its line), its
    verdict and its odometry residual RMS (cm)."""
    calib("run", rec, "-o", out, "-q")
    m = json.loads((out / "report" / "metrics.json").read_text())
    rep = json.loads((out / "calibration" / "report.json").read_text())
    return {**{k: np.nan if m.get(key) is None else m[key] * scale for k, (key, scale) in METRICS.items()},
            "verdict": rep["verdict"]["status"], "odo_cm": rep["residuals"]["odometry"]["rms_cm"]}


def board_arrays(sc, board):
    """The arrays of scenario ``sc`` given ``board``'s geometry: all, but the reference when the board is linear
    (a linear array measures cones, not directions: the reference must place the sources in its frame)."""
    mics = BOARDS[board].mic_array()
    linear = np.linalg.matrix_rank(mics - mics.mean(axis=0), tol=1e-9) < 2
    return [a["name"] for a in sc["arrays"] if not (linear and a["name"] == sc["reference_array"])]


def session(tmp, name, seed, args, board=None):
    """Simulate ``args.preset``; with a board, its arrays (:func:`board_arrays`) get the board's geometry.
    Returns (folder, names of the board's arrays)."""
    rec = tmp / name
    sc = make_scenario(args.preset, seed, n_events=args.n_events, interval=args.interval, chirp={"duration": args.chirp})
    names = board_arrays(sc, board) if board else []
    for a in sc["arrays"]:
        if a["name"] in names:
            a["mics"] = BOARDS[board].mic_array()
    simulate(sc, rec)
    return rec, names


def row(layout, seed, clean, conv):
    r = {"layout": layout, "seed": seed, "verdict": conv["verdict"], "odo_cm_clean": clean["odo_cm"],
         "odo_cm": conv["odo_cm"]}
    for k in METRICS:
        r[f"{k}_clean"], r[k], r[f"{k}_ratio"] = clean[k], conv[k], conv[k] / max(clean[k], 1e-12)
    print(f"{layout} seed {seed}: " + ", ".join(f"{k} {clean[k]:.3g} -> {conv[k]:.3g}" for k in METRICS),
          file=sys.stderr, flush=True)
    return r


def bag_rows(tmp, seed, args, rec, clean):
    rows = []
    for ros in (1, 2):
        dst = tmp / f"bag{ros}-{seed}"
        bag = layouts.to_bag(rec, dst, ros=ros, speaker_offset=LEVER_ARM, latency=LATENCY)
        calib("import-bag", bag, "-o", dst / "events.csv", "--emit-topic", "/chirp", "--latency", LATENCY, "-q")
        rows.append(row(f"ROS {ros} bag", seed, clean, errors(dst, tmp / f"out-bag{ros}-{seed}")))
    text = (dst / "session.toml").read_text()  # the same session, the lever arm not modelled
    (dst / "session.toml").write_text(re.sub(r"\n\[robot\]\nspeaker_offset = .*\n", "\n", text))
    rows.append(row("ROS 2 bag, no lever arm", seed, clean, errors(dst, tmp / f"out-nolever-{seed}")))
    # the lever arm again, the latency not given: every emission time LATENCY early (the robot stands still)
    (dst / "session.toml").write_text(text)
    calib("import-bag", bag, "-o", dst / "events.csv", "--emit-topic", "/chirp", "--force", "-q")
    rows.append(row("ROS 2 bag, latency not given", seed, clean, errors(dst, tmp / f"out-nolatency-{seed}")))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--boards", nargs="*", default=list(BOARDS), help="board models (none: only the other layouts)")
    ap.add_argument("--preset", default="lab3")
    ap.add_argument("--n-events", type=int, default=14)
    ap.add_argument("--interval", type=float, default=1.0)
    ap.add_argument("--chirp", type=float, default=0.2)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        for seed in args.seeds:
            for b in args.boards:
                rec, names = session(tmp, f"{b}-{seed}", seed, args, board=b)
                clean = errors(rec, tmp / f"out-{b}-{seed}")
                layouts.to_board_layout(rec, tmp / f"raw-{b}-{seed}", b, seed=seed, arrays=names)
                rows.append(row(f"raw {b}", seed, clean, errors(tmp / f"raw-{b}-{seed}", tmp / f"out-raw-{b}-{seed}")))
            rec, _ = session(tmp, f"default-{seed}", seed, args)
            clean = errors(rec, tmp / f"out-default-{seed}")
            layouts.to_per_mic(rec, tmp / f"permic-{seed}")
            rows.append(row("one file per mic", seed, clean, errors(tmp / f"permic-{seed}", tmp / f"out-pm-{seed}")))
            rows += bag_rows(tmp, seed, args, rec, clean)
    df = pd.DataFrame(rows)
    print(f"{args.preset}, {args.n_events} stops, chirp {args.chirp} s; lever arm {LEVER_ARM} m, latency "
          f"{LATENCY * 1e3:g} ms: calib run on the converted session vs on the clean one")
    cols = ["layout", "seed"] + [c for k in METRICS for c in (f"{k}_clean", k, f"{k}_ratio")] + \
        ["odo_cm_clean", "odo_cm", "verdict"]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    ratios = df[[f"{k}_ratio" for k in METRICS]]
    modelled = ~df["layout"].str.contains("no lever arm")  # (the latency not given: expected equal, see docs)
    ok = (ratios[modelled].fillna(1.0) <= TOLERANCE).all(axis=1)  # NaN: a metric neither run defines
    print(f"as accurate as the clean session (every ratio <= {TOLERANCE}): {int(ok.sum())}/{int(modelled.sum())}")
    worse = df.loc[~modelled]
    if len(worse):
        print("lever arm not modelled: array position error x"
              + ", ".join(f"{v:.2f}" for v in worse["loc_cm_ratio"]) + " of the clean session's; source error x"
              + ", ".join(f"{v:.2f}" for v in worse["src_cm_ratio"]) + "; odometry residual RMS "
              + ", ".join(f"{a:.2g} -> {b:.2g} cm" for a, b in zip(worse["odo_cm_clean"], worse["odo_cm"]))
              + "; verdicts " + ", ".join(worse["verdict"]))


if __name__ == "__main__":
    main()
