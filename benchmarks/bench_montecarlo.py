"""Monte-Carlo benchmark (issue #6): the paper's full protocol for both methods, its wall time, and the
Wang et al. baseline on the real data sets.

    python benchmarks/bench_montecarlo.py                    # 9 cells × 3 trajectories × 200 runs × 2 methods
    python benchmarks/bench_montecarlo.py --runs 20          # a tenth of it
    python benchmarks/bench_montecarlo.py --cost-split 10    # CPU cost of the convergence check and CRLB draw

Prints: wall time of the study (and whether it resumed), CPU time per calibration by method, then per cell
the IQR-means of both methods next to the CRLB and the paper's values, the worst ratios to the paper, and
the per-set real-data table (the paper: Wang et al. 9.3 cm / 6.28°, Zhang et al. 7.9 cm / 5.81°).
The study directory is kept (default /tmp/calib-bench-montecarlo): re-running resumes it; --fresh starts over.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd


from calib.estimator import calibrate
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.formats.io import read_features, read_truth
from calib.pipeline.montecarlo import _run_chunk, run_study
from realdata import not_found, real_world_dir  # noqa: E402 (benchmarks/, the script's folder)

REAL = real_world_dir()


def cost_split(runs):
    """CPU seconds per calibration with and without the truth-start check and the CRLB draw (one process)."""
    tasks = [(st, sd, tr, r, ["hybrid", "wang"]) for st, sd in [(5e-5, 5.0), (1e-4, 10.0), (5e-4, 15.0)]
             for tr in (1, 2, 3) for r in range(runs)]
    _run_chunk(tasks[:1], {"base_seed": 0, "sigma_odo": 0.03, "check_convergence": True, "with_crlb": True})
    rows = []
    for check, crlb in ((False, False), (False, True), (True, False), (True, True)):
        t0 = time.process_time()
        _run_chunk(tasks, {"base_seed": 0, "sigma_odo": 0.03, "check_convergence": check, "with_crlb": crlb})
        per = (time.process_time() - t0) / (2 * len(tasks))
        rows.append({"check_convergence": check, "crlb": crlb, "cpu_ms_per_calibration": 1e3 * per,
                     "projected_full_study_s_on_2_cores": per * 10800 / 2})
    return pd.DataFrame(rows)


def real():
    rows = []
    for d in sorted(REAL.glob("zhang_real_*")):
        feats, truth = read_features(d / "features"), read_truth(d / "truth")
        for method in ("hybrid", "wang"):
            try:
                m = evaluate(calibrate(feats, method=method), truth)
            except ValueError as exc:
                rows.append({"set": d.name, "method": method, "error": str(exc)})
                continue
            rows.append({"set": d.name, "method": method,
                         "loc_cm": 100 * np.mean([a["position_m"] for a in m["per_array"]]),
                         "ang_deg": np.mean([a["paper_deg"] for a in m["per_array"]])})
    return pd.DataFrame(rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200, help="runs per cell and trajectory")
    ap.add_argument("--jobs", type=int, default=-1)
    ap.add_argument("--out", type=Path, default=Path("/tmp/calib-bench-montecarlo"))
    ap.add_argument("--fresh", action="store_true", help="delete --out first (time the whole study)")
    ap.add_argument("--no-check-convergence", action="store_true")
    ap.add_argument("--no-crlb", action="store_true")
    ap.add_argument("--cost-split", type=int, default=0, metavar="N",
                    help="also time N runs per trajectory of 3 cells in one process with the checks on/off")
    ap.add_argument("--no-real", action="store_true")
    args = ap.parse_args()
    pd.set_option("display.width", 200)
    pd.set_option("display.max_columns", 40)
    fmt = lambda v: f"{v:.3g}"  # noqa: E731
    if args.fresh and args.out.exists():
        shutil.rmtree(args.out)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    def progress(done, total, msg):
        print(f"\r{done}/{total} calibrations ({msg})", end="", file=sys.stderr, flush=True)

    res = run_study(args.out, runs=args.runs, jobs=args.jobs, progress=progress,
                    check_convergence=not args.no_check_convergence, with_crlb=not args.no_crlb)
    wall = time.perf_counter() - t0
    runs, s = res["runs"], res["summary"]
    print(f"\n{res['computed']} calibrations computed, {res['skipped']} resumed, in {wall:.0f} s wall "
          f"(jobs={args.jobs}, {os.cpu_count()} cores; load average before {load0:.2f}, after "
          f"{os.getloadavg()[0]:.2f}; checks: convergence={not args.no_check_convergence}, crlb={not args.no_crlb})")
    final = runs[(runs["stage"] == "final") & runs["ok"]]
    print("time per calibration (s, wall inside a worker):")
    print(final.groupby("method")["time_s"].describe(percentiles=[0.5, 0.95]).to_string(float_format=fmt))
    s = s[s["stage"] == "final"]
    cols = ["sigma_tdoa_ms", "sigma_doa_deg", "method", "runs", "failed", "converged_pct", "loc_cm", "crlb_loc_cm",
            "paper_loc_cm", "ang_deg", "crlb_ang_deg", "paper_ang_deg", "geo_deg", "offset_1e-4s",
            "crlb_offset_1e-4s", "drift_ppm", "crlb_drift_ppm"]
    print(s[cols].to_string(index=False, float_format=fmt))
    h, w = s[s["method"] == "hybrid"].reset_index(drop=True), s[s["method"] == "wang"].reset_index(drop=True)
    print(f"\nhybrid vs paper (worst cell): location {(h['loc_cm'] / h['paper_loc_cm']).max():.3f}, "
          f"orientation {(h['ang_deg'] / h['paper_ang_deg']).max():.3f} (<= 1 is the target)")
    if len(w) == len(h):
        print(f"wang / hybrid over cells: location {(w['loc_cm'] / h['loc_cm']).min():.2f}-"
              f"{(w['loc_cm'] / h['loc_cm']).max():.2f}, orientation {(w['ang_deg'] / h['ang_deg']).min():.2f}-"
              f"{(w['ang_deg'] / h['ang_deg']).max():.2f}, offset {(w['offset_1e-4s'] / h['offset_1e-4s']).min():.2f}-"
              f"{(w['offset_1e-4s'] / h['offset_1e-4s']).max():.2f}")
    print("convergence (final cost within 1e-6 of the solve from ground truth): "
          + ", ".join(f"{m} {g['converged_pct'].min():.1f}-{g['converged_pct'].max():.1f} %"
                      for m, g in s.groupby("method")))
    if args.cost_split:
        print("\nCPU cost per calibration (one process, both methods averaged):")
        print(cost_split(args.cost_split).to_string(index=False, float_format=fmt))
    if not args.no_real and not REAL.exists():
        print(not_found(REAL))
    elif not args.no_real:
        r = real()
        print(f"\nreal data ({REAL}), mean over arrays per set:")
        print(r.to_string(index=False, float_format=fmt))
        ok = r.dropna(subset=["loc_cm"]) if "loc_cm" in r else r
        print(ok.groupby("method")[["loc_cm", "ang_deg"]].mean().to_string(float_format=fmt))
        print("paper: Zhang et al. 7.9 cm / 5.81 deg (12 of 15 sets converged), Wang et al. 9.3 cm / 6.28 deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
