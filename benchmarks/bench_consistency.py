"""The leave-one-array-out consistency test (issues 27/28, estimator/consistency.py): detections on faulty
sessions, false alarms on clean ones, what adopting a solution without the named array does to the others, and
the time it adds.

    python benchmarks/bench_consistency.py                 # 10 seeds per simulated case + the real sets
    python benchmarks/bench_consistency.py --seeds 4       # quicker
    python benchmarks/bench_consistency.py --sessions 'DIR/os_lab*/features:DIR/s_lab*/truth'   # + stored sessions
    python benchmarks/bench_consistency.py --cli FEATURES  # + `calib estimate` on a features folder (subprocess)

Every run is calibrated twice from the same features: without the test (``clockmodel.calibrate_clocks`` around
``calibrate_features``, what calibrate returned before) and with it (``calibrate``). Cases (feature level,
``featsim``): ``clean-paper`` (the paper's protocol, trajectories 1-3), ``clean-session`` (issue 28's 3-minute
session of benchmarks/bench_clocks.py), ``warmup-linear`` (that session with A3's drift settling by 30 ppm over
a minute, calibrated with the linear clock, which cannot model it: A3's rows are biased with the geometry),
``warmup-auto`` (the same with the clock model chosen by the evidence), ``real`` (the eight real feature sets),
``stored`` (``--sessions``: features:truth folder pairs, globs matched in sorted order).

Columns: runs; ``named``: runs where the test named an array (a false alarm on the clean cases: the family-wise
level is robust.FAMILY_ALPHA = 1 % per run); ``planted``: runs whose verdict names the planted array (any
test); ``isolated``: runs solved without a named array; ``ok``: runs with verdict ok before → after;
``worst_z``: the largest position error / stated std of an array the verdict does not flag, before → after;
``rms_cm``: RMS position error of the arrays not flagged after, before → after (same arrays); ``added``: mean
CPU time the test adds (with − without; includes the re-solves of a named array) / mean CPU time of the
calibration with it (process CPU s; wall time on a shared machine is noisier).
"""
from __future__ import annotations

import argparse
import glob
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from calib.blas import single_thread_blas
from calib.estimator import calibrate, clockmodel
from calib.estimator.calibrate import calibrate_features
from calib.pipeline.formats.io import read_features, read_truth
from calib.pipeline.simulate.featsim import simulate_features

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_clocks import scene  # noqa: E402
from cliproc import calib_cmd, load, measure  # noqa: E402
from realdata import not_found, real_world_dir  # noqa: E402

PLANTED = "A3"
WARMUP = {PLANTED: {"warmup": {"amplitude": 3e-5, "time_constant": 60.0}}}


def cases(seeds, sessions):
    """{case: [(label, features, truth, options, planted array or None)]} (lazily drawn: generators)."""
    def paper():
        for s in seeds:
            yield (f"paper {s}", *simulate_features(1 + s % 3, seed=s), {}, None)

    def session():
        for s in seeds:
            yield (f"session {s}", *scene(s), {}, None)

    def warm(clock):
        for s in seeds:
            yield (f"warm-up {s}", *scene(s, clocks=WARMUP), {"clock_model": clock}, PLANTED)

    def real():
        d = real_world_dir()
        sets = sorted(d.glob("zhang_real_*"))
        if not sets:
            print(not_found(d))
        for p in sets:
            yield (p.name, read_features(p / "features"), read_truth(p / "truth"), {}, None)

    def stored():
        for pair in sessions:
            f, t = pair.split(":")
            for a, b in zip(sorted(glob.glob(f)), sorted(glob.glob(t))):
                yield (a, read_features(a), read_truth(b), {}, None)

    out = {"clean-paper": paper(), "clean-session": session(), "warmup-linear": warm("linear"),
           "warmup-auto": warm("auto"), "real": real()}
    if sessions:
        out["stored"] = stored()
    return out


def scores(r, truth, flagged):
    """({array: error / std} of the arrays not in ``flagged``, {array: error m})."""
    t = truth["arrays"].set_index("array")
    a = r["arrays"].set_index("array")
    err, z = {}, {}
    for n in a.index:
        e = float(np.linalg.norm(a.loc[n, ["x", "y", "z"]].to_numpy(float) - t.loc[n, ["x", "y", "z"]].to_numpy(float)))
        sd = float(np.sqrt(np.nansum(a.loc[n, ["x_std", "y_std", "z_std"]].to_numpy(float) ** 2)))
        err[n] = e
        if n not in flagged and sd > 0:
            z[n] = e / sd
    return z, err


def one(f, truth, options, planted):
    """The figures of one run, before and after."""
    t0 = time.process_time()
    with single_thread_blas():
        before = clockmodel.calibrate_clocks(calibrate_features, f, **options)
    t1 = time.process_time()
    after = calibrate(f, **options)
    cpu, cpu0 = time.process_time() - t1, t1 - t0
    rep = after["report"]
    loo = rep["leave_one_out"]
    v0, v1 = before["report"]["verdict"], rep["verdict"]
    z0, e0 = scores(before, truth, v0["flagged_arrays"])
    z1, e1 = scores(after, truth, v1["flagged_arrays"])
    keep = [n for n in e1 if n not in v1["flagged_arrays"]]
    return {"named": bool(loo["inconsistent"]), "planted": planted in v1["flagged_arrays"] if planted else None,
            "isolated": any(t["isolated"] for t in loo["inconsistent"]),
            "ok0": v0["status"] == "ok", "ok1": v1["status"] == "ok",
            "z0": max(z0.values(), default=0.0), "z1": max(z1.values(), default=0.0),
            "sq0": [e0[n] ** 2 for n in keep], "sq1": [e1[n] ** 2 for n in keep],
            "added_s": cpu - cpu0, "cpu_s": cpu}


def row(name, runs):
    n = len(runs)
    planted = [r["planted"] for r in runs if r["planted"] is not None]
    rms = [np.sqrt(np.mean(sum((r[k] for r in runs), []) or [np.nan])) * 100 for k in ("sq0", "sq1")]
    return (f"| {name} | {n} | {sum(r['named'] for r in runs)} | "
            f"{f'{sum(planted)}' if planted else '–'} | {sum(r['isolated'] for r in runs)} | "
            f"{sum(r['ok0'] for r in runs)} → {sum(r['ok1'] for r in runs)} | "
            f"{max(r['z0'] for r in runs):.1f} → {max(r['z1'] for r in runs):.1f} | {rms[0]:.2f} → {rms[1]:.2f} | "
            f"{np.mean([r['added_s'] for r in runs]):.3f} / {np.mean([r['cpu_s'] for r in runs]):.2f} s |")


def cli(features):
    """`calib estimate` on a features folder in a subprocess: its verdict line and times."""
    import json
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        m = measure(calib_cmd("estimate", features, "-o", Path(d) / "calibration", "-q"))
        rep = json.loads((Path(d) / "calibration" / "report.json").read_text()) if m["rc"] in (0, 3) else {}
    loo = rep.get("leave_one_out", {})
    print(f"\n`calib estimate {features}`: exit {m['rc']}, wall {m['wall_s']:.2f} s, cpu {m['cpu_s']:.2f} s, "
          f"verdict {rep.get('verdict', {}).get('status')}, named "
          f"{[t['array'] for t in loo.get('inconsistent', [])]}, test {loo.get('time_s', 0):.2f} s")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--cases", nargs="*", help="only these cases")
    ap.add_argument("--sessions", nargs="*", default=[], help="FEATURES_GLOB:TRUTH_GLOB pairs (stored sessions)")
    ap.add_argument("--cli", nargs="*", default=[], help="features folders to run `calib estimate` on")
    a = ap.parse_args()
    warnings.filterwarnings("ignore")
    print(f"load: {load()}")
    print("| case | runs | named | planted | isolated | ok before → after | worst_z unflagged | rms_cm | added test / calibration |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, gen in cases(range(a.seeds), a.sessions).items():
        if a.cases and name not in a.cases:
            continue
        runs = [one(f, t, o, pl) for _, f, t, o, pl in gen]
        if runs:
            print(row(name, runs), flush=True)
    for f in a.cli:
        cli(f)


if __name__ == "__main__":
    main()
