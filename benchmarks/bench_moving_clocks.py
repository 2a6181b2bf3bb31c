"""A clock step in a session where the robot moves while it chirps (issue 28, acceptance for moving sessions).

    python benchmarks/bench_moving_clocks.py --seeds 8 --first-seed 100
    python benchmarks/bench_moving_clocks.py --sizes 2 -20 --seeds 4   # some sizes only (ms, > 0 inserted)

The scene is test_motion_noise's moving one (tests/test_clocks.py ``_moving_scene``): featsim trajectory 2 (10
events over ~54 s, 5 arrays, σ_TDOA 2 µs, σ_DOA 0.05°, σ_odo 1 cm), every arrival shifted by β ṙ/c as a robot
that keeps moving while it chirps leaves it, events.csv with the velocity off by σ_v = 0.05 m/s per axis and that
σ_v stated (``motion.velocity_sigma``). Per seed and size a block of samples is dropped (< 0) or inserted (> 0)
on an array drawn among all (the reference included) in an interval drawn among those with at least
MIN_SIDE events on each side; each faulty session is compared with the same session without the fault.
``calibrate`` takes `calib run`'s estimator options (``pipeline.run.estimate_defaults``).

Columns per run: found (a step on the faulty array), in the right interval, (size − true) / σ, the faulty
array's position error (cm) with the fault / without, the other arrays' RMS position error with / without, the
arrays named unreliable, anything else modelled, CPU s. The summary: the acceptance items (found in the right
interval, size within 3σ, runs within 1.5× (+2 mm) of the fault-free session, the faulty array kept).
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from calib.estimator import calibrate
from calib.estimator.clockmodel import Component, correct_features
from calib.pipeline.report.evaluate import array_errors, array_table, evaluate
from calib.pipeline.run import estimate_defaults
from calib.pipeline.simulate.featsim import simulate_features

SIGMA_V = 0.05        # m/s per axis: the velocity error of test_motion_noise's moving scene
SIZES_MS = (0.5, -0.5, 2.0, -2.0, 20.0, -20.0)
MIN_SIDE = 3          # events on each side of the step (nearer an end the DOA test decides: not this bench)


def moving_scene(seed, sigma_v=SIGMA_V):
    """(features, truth) of the moving scene (as tests/test_clocks.py ``_moving_scene``, without pytest)."""
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    from tests.test_motion_nlos import _moving

    f, tr = simulate_features(2, 2e-6, 0.05, 0.01, seed=seed)
    vel_error = np.random.default_rng(100 + seed).normal(0.0, sigma_v, (len(f["events"]), 3))
    return _moving(f, tr, with_vel=True, vel_error=vel_error)[0], tr


def state_sigma_v(sigma_v=SIGMA_V):
    """The stated velocity σ of the scene (the estimator's own figure from the odometry otherwise)."""
    import calib.estimator.motion as motion

    motion.velocity_sigma = lambda *a, **k: sigma_v


def fault(seed, size_ms, f):
    """(array, k, features with ``size_ms`` of samples on ``array`` between events k − 1 and k)."""
    rng = np.random.default_rng([seed, 2842, int(round(abs(size_ms) * 10)), int(size_ms < 0)])
    names = list(f["meta"]["arrays"])
    array = names[int(rng.integers(len(names)))]
    t = f["events"]["t_emit"].to_numpy(float)
    k = int(rng.integers(MIN_SIDE, len(t) - MIN_SIDE + 1))
    step = Component("step", 0.5 * (t[k - 1] + t[k]) - t[0], -size_ms * 1e-3)   # correct_features removes it
    return array, k, correct_features(f, {array: [step]})


def options(noise=None):
    """`calib run`'s estimator options; ``noise``: instead of its "auto" (feature-level scenes state their σ:
    "meta"; a frontend's estimated σ give "estimate")."""
    o = estimate_defaults()
    o["loss"] = None if o["loss"] == "linear" else o["loss"]
    return {**o, **({"noise": noise} if noise else {})}


def _errors(cal, truth):
    e = array_errors(array_table(cal["arrays"]), array_table(truth["arrays"]))
    return dict(zip(e["array"], np.asarray(e["position_m"], float)))


def run_one(seed, size_ms, base, opts):
    f0, truth, c0 = base
    array, k, f = fault(seed, size_ms, f0)
    t = time.process_time()
    cal = calibrate(f, **opts)
    cpu = time.process_time() - t
    rep = cal["report"]["clock"]
    ev = f["events"]["event"].to_numpy()
    steps = rep["arrays"][array]["steps"]
    hit = [s for s in steps if (s["after_event"], s["before_event"]) == (ev[k - 1], ev[k])]
    e, e0 = _errors(cal, truth), _errors(c0, truth)
    others = [n for n in e if n != array]
    rms = lambda d: float(np.sqrt(np.mean([d[n] ** 2 for n in others])))   # noqa: E731
    other_terms = [n for n, a in rep["arrays"].items() if a["components"] and n != array]
    other_terms += ["emitter"] if rep["emitter"]["components"] else []
    rep0 = c0["report"]["clock"]
    clean_terms = [n for n, a in rep0["arrays"].items() if a["components"]] + (["emitter"] if rep0["emitter"]["components"] else [])
    return {"seed": seed, "size_ms": size_ms, "array": array, "k": k, "found": bool(steps), "interval": bool(hit),
            "n_steps": len(steps), "other_terms": other_terms, "clean_terms": clean_terms,
            "z": (hit[0]["size"] - size_ms * 1e-3) / hit[0]["std"] if hit and hit[0]["std"] else float("nan"),
            "got_ms": [s["size"] * 1e3 for s in steps], "std_us": [(s["std"] or np.nan) * 1e6 for s in steps],
            "faulty_cm": 100 * e.get(array, np.nan), "faulty0_cm": 100 * e0.get(array, np.nan),
            "others_cm": 100 * rms(e), "others0_cm": 100 * rms(e0),
            "loc_cm": 100 * evaluate(cal, truth)["position_rmse_m"], "loc0_cm": 100 * evaluate(c0, truth)["position_rmse_m"],
            "unreliable": list(cal["report"]["unreliable_arrays"]), "unreliable0": list(c0["report"]["unreliable_arrays"]),
            "cpu_s": cpu}


def row_text(r):
    ok = r["interval"] and abs(r["z"]) < 3 and r["array"] not in r["unreliable"] and \
        r["loc_cm"] <= 1.5 * r["loc0_cm"] + 0.2 and not r["other_terms"]
    got = ", ".join(f"{g:+.3f}±{s:.1f}µs" for g, s in zip(r["got_ms"], r["std_us"])) or "-"
    return (f"| {r['seed']} | {r['size_ms']:+g} | {r['array']} | {r['k'] - 1}-{r['k']} | {got} | "
            f"{'yes' if r['interval'] else 'no'} | {r['z']:+.1f} | {r['faulty_cm']:.2f} / {r['faulty0_cm']:.2f} | "
            f"{r['others_cm']:.2f} / {r['others0_cm']:.2f} | {r['loc_cm']:.2f} / {r['loc0_cm']:.2f} | "
            f"{','.join(r['unreliable']) or '-'} / {','.join(r['unreliable0']) or '-'} | {','.join(r['other_terms']) or '-'} | {r['cpu_s']:.0f} | "
            f"{'ok' if ok else 'FAIL'} |")


def summary(rows):
    n = len(rows)
    right = sum(r["interval"] for r in rows)
    sized = sum(r["interval"] and abs(r["z"]) < 3 for r in rows)
    within = sum(r["loc_cm"] <= 1.5 * r["loc0_cm"] + 0.2 for r in rows)
    kept = sum(r["array"] not in r["unreliable"] for r in rows)
    kept0 = sum(r["array"] not in r["unreliable0"] for r in rows)
    other = sum(bool(r["other_terms"]) for r in rows)
    clean = {r["seed"]: bool(r["clean_terms"]) for r in rows}
    return (f"runs {n}: found in the right interval {right}/{n}, size within 3σ {sized}/{n}, within 1.5× (+2 mm) of "
            f"the fault-free session {within}/{n}, faulty array kept {kept}/{n} (fault-free: {kept0}/{n}), anything else modelled {other}/{n}; "
            f"fault-free sessions with a clock term {sum(clean.values())}/{len(clean)}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=100)
    ap.add_argument("--sizes", type=float, nargs="*", default=list(SIZES_MS), help="ms, > 0 inserted")
    ap.add_argument("--save", help="write the rows as JSON here")
    ap.add_argument("--noise", choices=["meta", "estimate"], help="instead of calib run's auto (here: meta)")
    a = ap.parse_args()
    state_sigma_v()
    opts = options(a.noise)
    print(f"moving scene, seeds {a.first_seed}..{a.first_seed + a.seeds - 1}, sizes {a.sizes} ms, noise {opts['noise']}; "
          f"load {os.getloadavg()[0]:.1f}\n")
    print("| seed | ms | array | interval | steps found (ms ± σ) | right interval | (size − true)/σ | "
          "faulty array cm fault / clean | others cm fault / clean | RMS cm fault / clean | unreliable fault / clean | "
          "other terms | CPU s | |")
    print("|" + "---|" * 14)
    rows = []
    for seed in range(a.first_seed, a.first_seed + a.seeds):
        f0, truth = moving_scene(seed)
        base = (f0, truth, calibrate(f0, **opts))
        for size in a.sizes:
            rows.append(run_one(seed, size, base, opts))
            print(row_text(rows[-1]), flush=True)
    print("\n" + summary(rows) + f"; load {os.getloadavg()[0]:.1f}")
    if a.save:
        with open(a.save, "w") as fh:
            json.dump(rows, fh, indent=1, default=float)


if __name__ == "__main__":
    main()
