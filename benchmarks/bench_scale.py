"""Estimator at scale (issues #12, #32): `calib estimate` time, CPU, peak memory (measured and predicted by the
memory check) and accuracy vs the CRLB, arrays × events.

    python benchmarks/bench_scale.py                 # arrays {3,5,10,20,40} x events {14,50,100,200,500,1000}
    python benchmarks/bench_scale.py --quick         # a subset (a few minutes)
    python benchmarks/bench_scale.py --arrays 40 --events 1000
    python benchmarks/bench_scale.py --arrays 100 --events 5000 --no-crlb   # the envelope (issue 32: <= 120 s, 4 GB)
    python benchmarks/bench_scale.py --library       # calibrate() in a subprocess per case instead of the CLI
    python benchmarks/bench_scale.py --dense-check   # sparse vs dense solver on small scenes

By default every case runs the user's path: the features are written to a folder and ``calib estimate FEATURES
-o CALIB -q`` runs as its own process (import, reading and validating the CSVs, the memory check, the
calibration, calibration.json and the report files included); ``wall_s``, ``cpu_s`` (user + system) and
``peak_mb`` are that process's (``os.wait4``), ``pred_mb`` is what the memory check
(``pipeline.formats.validate.estimator_memory``) predicted for it. Accuracy is scored from the written
arrays.csv / sources.csv against the CRLB computed here.

Scenes (feature level, ``pipeline.simulate.featsim``): arrays on a grid in a room whose side grows with the number
of arrays (6 m for 3 arrays to 20 m for 40), at 1–2.5 m height, random orientations; a robot drives a
random smooth path inside the room and chirps every 0–4 s; noise 0.1 ms (TDOA), 5° (DOA), 3 cm (odometry
per step). Every case runs in its own subprocess (one calibration at a time, BLAS single-threaded as the
estimator pins it), so the peak resident memory (ru_maxrss) is that calibration's plus the interpreter.
Columns: ``wall_s`` and ``cpu_s`` (process CPU time: the wall time an idle machine would show, the estimator
being single-threaded) of one calibration, stage wall times in s (report ``timings_s``; ``crlb_s`` is the
bound, not part of the calibration),
peak RSS in MB, array position / orientation and source errors as ratios to the CRLB's RMS prediction
(≈ 1 means at the bound), and whether the solve converged.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ARRAYS = (3, 5, 10, 20, 40)
EVENTS = (14, 50, 100, 200, 500, 1000)
QUICK = [(5, 14), (5, 100), (10, 200), (20, 500), (40, 200), (40, 500), (40, 1000)]
SIGMA_TDOA, SIGMA_DOA_DEG, SIGMA_ODO = 1e-4, 5.0, 0.03
ROOM_MIN, ROOM_MAX = 6.0, 20.0      # room side (m)
CLEARANCE = 0.5                     # no source closer than this to an array (m)
STEP = 0.6                          # mean robot step between chirps (m)
MAX_INTERVAL = 4.0                  # chirp intervals uniform in (0, 4) s: one every 2 s on average


def scene(n_arrays, n_events, seed=0):
    """Array positions (N, 3) (reference at the origin) and source stops (K, 3) of one scale scene."""
    rng = np.random.default_rng(seed)
    side = float(np.clip(3.0 * np.sqrt(n_arrays), ROOM_MIN, ROOM_MAX))
    nx = int(np.ceil(np.sqrt(n_arrays)))
    ny = int(np.ceil(n_arrays / nx))
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) / nx * side, (np.arange(ny) + 0.5) / ny * side, indexing="ij")
    x = np.column_stack([gx.ravel(), gy.ravel(), rng.uniform(1.0, 2.5, nx * ny)])[:n_arrays]
    stops = np.zeros((n_events, 3))
    pos, heading = np.array([side / 2 + 0.3, side / 2 + 0.3, 1.0]), rng.uniform(0, 2 * np.pi)
    for k in range(n_events):
        for _ in range(100):  # turn until the next stop is inside the room and clear of every array
            heading += rng.normal(0, 0.6)
            nxt = pos + STEP * rng.uniform(0.5, 1.5) * np.array([np.cos(heading), np.sin(heading), 0.0])
            nxt[2] = np.clip(pos[2] + rng.normal(0, 0.3), 0.3, 2.2)
            inside = np.all(nxt[:2] > 0.3) and np.all(nxt[:2] < side - 0.3)
            if inside and np.min(np.linalg.norm(x - nxt, axis=1)) > CLEARANCE:
                break
        pos = nxt
        stops[k] = pos
    return x - x[0], stops - x[0]


def features(n_arrays, n_events, seed=0):
    """(features, truth) of a scale scene, via ``pipeline.simulate.featsim.simulate_features``."""
    from calib.pipeline.simulate.featsim import simulate_features

    x, stops = scene(n_arrays, n_events, seed)
    return simulate_features(stops, SIGMA_TDOA, SIGMA_DOA_DEG, SIGMA_ODO, seed=seed + 1, positions=x,
                             max_interval=MAX_INTERVAL)


def _rms_ratio(err, cov_blocks):
    """RMS error norm over items / RMS predicted by (k, 3, 3) covariance blocks."""
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)) / np.mean(np.trace(cov_blocks, axis1=1, axis2=2))))


def run_case(n_arrays, n_events, seed=0, with_crlb=True):
    """One calibration of one scene: timings, peak memory and accuracy (dict)."""
    from scipy.spatial.transform import Rotation

    from calib.estimator import calibrate, crlb
    from calib.estimator.uncertainty import cov_block

    feats, truth = features(n_arrays, n_events, seed)
    t0, c0 = time.perf_counter(), time.process_time()
    cal = calibrate(feats)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rep = cal["report"]
    row = {"arrays": n_arrays, "events": n_events, "wall_s": wall, "cpu_s": cpu,
           **{f"{k}_s": v for k, v in rep["timings_s"].items() if k != "total"},
           "converged": rep["converged"], "iterations": rep["iterations"]["final"],
           "chi2_dof": rep["chi2_per_dof"]}
    if with_crlb:
        t1 = time.perf_counter()
        b = crlb(feats, truth)
        row["crlb_s"] = time.perf_counter() - t1
        lay, st, est = b["layout"], b["state"], cal["state"]
        arr = [i for i in range(n_arrays) if np.all(lay.x[i] >= 0)]
        ca = np.array([cov_block(b["cov"], lay.x[i]) for i in arr])
        row["pos_vs_crlb"] = _rms_ratio(est["x"][arr] - st.x[arr], ca)
        rot_err = (Rotation.from_matrix(st.R[arr]).inv() * Rotation.from_matrix(est["R"][arr])).as_rotvec()
        cr = np.array([cov_block(b["cov"], lay.rot[i]) for i in arr])
        row["rot_vs_crlb"] = _rms_ratio(rot_err, cr)
        cs = np.array([cov_block(b["cov"], lay.s[j]) for j in range(n_events)])
        row["src_vs_crlb"] = _rms_ratio(est["s"] - st.s, cs)
        row["pos_err_cm"] = 100 * float(np.sqrt(np.mean(np.sum((est["x"][arr] - st.x[arr]) ** 2, axis=1))))
    row["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return row


def dense_check(cases=((3, 14), (5, 14), (5, 50), (10, 50)), seed=0):
    """Sparse vs dense solver from the same start: cost and parameter differences (in σ)."""
    from calib.estimator.problem import build_problem, make_layout
    from calib.estimator.solver import levenberg_marquardt, linearise
    from calib.estimator.uncertainty import covariance, std_from_cov, state_from_frames

    kinds = ["tdoa_s", "tdoa_m", "doa", "odometry"]
    for n_arrays, n_events in cases:
        feats, truth = features(n_arrays, n_events, seed)
        p = build_problem(feats)
        st = state_from_frames(p, truth["arrays"], truth["sources"]).copy()
        lay = make_layout(p)
        res = {d: levenberg_marquardt(p, st.copy(), lay, kinds, dense=d) for d in (True, False)}
        J = linearise(p, res[True][0], lay, kinds, dense=True).J
        sd = std_from_cov(p, lay, covariance(J, lay.n))
        st_d, st_s = res[True][0], res[False][0]   # (State objects: fields by attribute)
        dx = max(np.nanmax(np.abs(getattr(st_d, k) - getattr(st_s, k)) / sd[k]) for k in ("x", "s", "offset"))
        c1, c2 = res[True][1]["cost"], res[False][1]["cost"]
        print(f"{n_arrays:3d} x {n_events:4d}: n={lay.n:5d} cost rel diff {abs(c1 - c2) / c1:.1e}, "
              f"max param diff {dx:.1e} sigma")


def _subprocess_case(n_arrays, n_events, seed, with_crlb):
    cmd = [sys.executable, str(Path(__file__).resolve()), "--case", str(n_arrays), str(n_events), "--seed", str(seed)]
    if not with_crlb:
        cmd.append("--no-crlb")
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        return {"arrays": n_arrays, "events": n_events, "error": out.stderr.strip().splitlines()[-1:]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def cli_case(n_arrays, n_events, seed=0, with_crlb=True):
    """One scene through ``calib estimate`` in its own process: wall, CPU, peak RSS, predicted memory,
    stage times (report.json) and accuracy vs the CRLB (dict)."""
    import tempfile

    from cliproc import calib_cmd, measure

    from calib.pipeline.formats.io import measurement_rows, read_calibration, write_features_files
    from calib.pipeline.formats.validate import estimator_memory

    feats, truth = features(n_arrays, n_events, seed)
    with tempfile.TemporaryDirectory(prefix="calib-bench-scale-") as tmp:
        fdir, cdir = Path(tmp) / "features", Path(tmp) / "calibration"
        fdir.mkdir()
        write_features_files(fdir, feats)
        m = measure(calib_cmd("estimate", fdir, "-o", cdir, "-q"))
        row = {"arrays": n_arrays, "events": n_events, "rc": m["rc"], "wall_s": m["wall_s"], "cpu_s": m["cpu_s"],
               "peak_mb": m["peak_mb"],
               "pred_mb": estimator_memory(n_events, n_arrays, measurement_rows(feats)) / 2**20}
        row["pred/peak"] = row["pred_mb"] / row["peak_mb"]
        if m["rc"] not in (0, 3):
            row["error"] = (m["stderr"].strip().splitlines() or ["?"])[-1]
            return row
        cal = read_calibration(cdir)
    rep = cal["report"]
    row.update({f"{k}_s": v for k, v in rep["timings_s"].items() if k != "total"})
    row.update({"verdict": rep["verdict"]["status"], "converged": rep["converged"]})
    if with_crlb:
        row.update(_accuracy(feats, truth, cal))
    return row


def _accuracy(feats, truth, cal):
    """Array position / rotation and source errors of a written calibration as ratios to the CRLB's RMS."""
    from scipy.spatial.transform import Rotation

    from calib.estimator import crlb
    from calib.estimator.uncertainty import cov_block, state_from_frames

    b = crlb(feats, truth)
    lay, st = b["layout"], b["state"]
    est = state_from_frames(b["problem"], cal["arrays"], cal["sources"])
    arr = [i for i in range(len(st.x)) if np.all(lay.x[i] >= 0)]
    ca = np.array([cov_block(b["cov"], lay.x[i]) for i in arr])
    rot_err = (Rotation.from_matrix(st.R[arr]).inv() * Rotation.from_matrix(est.R[arr])).as_rotvec()
    cr = np.array([cov_block(b["cov"], lay.rot[i]) for i in arr])
    cs = np.array([cov_block(b["cov"], lay.s[j]) for j in range(len(st.s))])
    return {"pos_vs_crlb": _rms_ratio(est.x[arr] - st.x[arr], ca), "rot_vs_crlb": _rms_ratio(rot_err, cr),
            "src_vs_crlb": _rms_ratio(est.s - st.s, cs),
            "pos_err_cm": 100 * float(np.sqrt(np.mean(np.sum((est.x[arr] - st.x[arr]) ** 2, axis=1))))}


def plot(rows, path):
    """Time vs number of events, one line per array count (log-log), to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for n in sorted({r["arrays"] for r in rows}):
        rr = sorted([r for r in rows if r["arrays"] == n and "wall_s" in r], key=lambda r: r["events"])
        ax.plot([r["events"] for r in rr], [r["cpu_s"] for r in rr], "o-", label=f"{n} arrays")
    ax.plot([14, 1000], [0.1 * 14 / 100, 0.1 * 10], "k:", lw=1, label="∝ events")
    ax.set(xscale="log", yscale="log", xlabel="events", ylabel="CPU time, user + system (s)",
           title="calib estimate (whole process): time vs problem size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help=f"only {QUICK}")
    ap.add_argument("--arrays", type=int, nargs="*", default=list(ARRAYS))
    ap.add_argument("--events", type=int, nargs="*", default=list(EVENTS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-crlb", action="store_true", help="skip the CRLB (accuracy columns)")
    ap.add_argument("--plot", type=Path, default=None, help="PNG of time vs size (docs/bench_scale.png: the "
                                                            "results page's)")
    ap.add_argument("--dense-check", action="store_true", help="sparse vs dense solver on small scenes")
    ap.add_argument("--library", action="store_true", help="calibrate() in a subprocess per case, not the CLI")
    ap.add_argument("--case", type=int, nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        print(json.dumps(run_case(*args.case, seed=args.seed, with_crlb=not args.no_crlb)))
        return 0
    if args.dense_check:
        dense_check(seed=args.seed)
        return 0

    import pandas as pd

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from cliproc import load

    cases = QUICK if args.quick else [(a, e) for a in args.arrays for e in args.events]
    rows = []
    print(f"{'calibrate() per subprocess' if args.library else 'calib estimate as a process'}; start: {load()}")
    for a, e in cases:
        rows.append(_subprocess_case(a, e, args.seed, not args.no_crlb) if args.library
                    else cli_case(a, e, args.seed, not args.no_crlb))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 30)
    print(pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"end: {load()} (wall times grow with the load; cpu_s is user + system CPU of the process)")
    if args.plot is not None:
        plot(rows, args.plot)
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
