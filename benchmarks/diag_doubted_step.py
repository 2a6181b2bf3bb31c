"""A clock step inside a run of events the frontend doubts (issue 28): a 508 µs step (an ESP board) on a random
non-reference array (or the reference, --ref), the run of its events doubted nlos (--lo events before the step,
--hi after), or, with --reflect R, no step but those arrivals late by U(R, 4R) each (reflections). Per seed: the
step found in its interval or not, the arrays modelled, the stepped array's and the others' error against the same
scene without the fault (cm), the verdict and the arrays refitted alone.

    python benchmarks/diag_doubted_step.py 570 20 --lo 6 --hi 0
"""
import sys, argparse
sys.path.insert(0, __import__("os").path.dirname(__file__))
import numpy as np
import pandas as pd
import bench_clocks as b
from calib.estimator import calibrate
from calib.pipeline.simulate.clocks import doubt_arrivals
from calib.pipeline.report.evaluate import array_errors, array_table
ap = argparse.ArgumentParser(); ap.add_argument("first", type=int); ap.add_argument("n", type=int)
ap.add_argument("--lo", type=int, default=3); ap.add_argument("--hi", type=int, default=3)
ap.add_argument("--ref", action="store_true"); ap.add_argument("--size", type=float, default=-5.08e-4)
ap.add_argument("--near-end", type=int, default=0, help="step this many events before the end")
ap.add_argument("--reflect", type=float, default=0.0, help="no step: the run's arrivals late by U(r, 4r) s each")
a = ap.parse_args()
for s in range(a.first, a.first + a.n):
    rng = np.random.default_rng([s, 51])
    name = "A1" if a.ref else f"A{2 + rng.integers(4)}"
    f0, t0 = b.scene(s)
    tt = f0["events"]["t_emit"].to_numpy() - f0["events"]["t_emit"].iloc[0]
    K = len(tt)
    k = K - a.near_end if a.near_end else int(rng.integers(10, K - 10))   # first event after the step
    time = 0.5 * (tt[k - 1] + tt[k])
    ev = f0["events"]["event"].to_numpy()
    run = ev[max(0, k - a.lo):min(K, k + a.hi)]
    if a.reflect:
        from calib.pipeline.simulate.clocks import delay_arrivals
        f, t = delay_arrivals(f0, name, {int(j): rng.uniform(a.reflect, 4 * a.reflect) for j in run}), t0
    else:
        f, t = b.scene(s, {name: {"steps": [{"size": a.size, "time": time}]}})
    if len(run):
        f = doubt_arrivals(f, name, run)
        if name == "A1":   # the reference's arrival is in every TDOA-M at those events (frontend: all flagged)
            tm = f["tdoa_m"].copy()
            old = tm["flag"].fillna("").astype(str) if "flag" in tm else pd.Series("", index=tm.index)
            add = tm["event"].isin(run) & ~old.str.contains("nlos")
            tm["flag"] = np.where(add, np.where(old == "", "nlos", old + "+nlos"), old)
            f = {**f, "tdoa_m": tm}
    cal = calibrate(f, clock_model="auto"); c0 = calibrate(f0, clock_model="linear")
    e = array_errors(array_table(cal["arrays"]), array_table(t["arrays"]))
    e0 = array_errors(array_table(c0["arrays"]), array_table(t0["arrays"]))
    i = list(e["array"]).index(name) if name in list(e["array"]) else -1
    oth = [j for j in range(len(e["array"])) if j != i and e["array"][j] != "A1"]
    got = [(x["after_event"], x["before_event"], round(x["size"] * 1e6, 1), round((x["std"] or 0) * 1e6, 1))
           for n, x2 in cal["report"]["clock"]["arrays"].items() for x in x2["steps"] if n == name]
    other = [n for n, x2 in cal["report"]["clock"]["arrays"].items() if (x2["steps"] or x2["drift_terms"]) and n != name]
    ok = any(g[:2] == (int(ev[k - 1]), int(ev[k])) for g in got)
    print(s, name, f"step ({ev[k-1]},{ev[k]}) run {run[0] if len(run) else '-'}-{run[-1] if len(run) else '-'}",
          "FOUND" if ok else "miss", got, "other:", other,
          f"own {100*e['position_m'][i]:.2f}/{100*e0['position_m'][i]:.2f}" if i >= 0 else "ref",
          f"others {100*np.sqrt(np.mean(np.array(e['position_m'])[oth]**2)):.2f}/{100*np.sqrt(np.mean(np.array(e0['position_m'])[oth]**2)):.2f}",
          cal["report"]["verdict"]["status"], cal["report"]["unreliable_arrays"], flush=True)
