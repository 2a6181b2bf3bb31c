"""A source moving during the sweep: its arrivals timed again with stretches PREDICTED from a first solve.

The frontend times every arrival against the template stretched by the Doppler factor ``1 + ε`` its own
arrival matches best (``frontend.timing.matched_stretch``). Where the direct path is heard below a reflection
(a wall-mounted array the robot drives away from, behind the directional speaker) that search takes the
reflection's ε, and the direct path's timing and DOA follow a smeared pulse. But ε is not free: it is
``ṙ_ij / c`` (+ the array's clock drift), ``ṙ`` the range rate the robot's velocity (events.csv / odometry)
and the direction from the source to the array give (``estimator.motion.predicted_stretches``), and a first
solve knows that direction to a degree or two: 0.5 m/s × 2° ≈ 0.02 m/s, 6e-5 in ε, below half a step of the
frontend's Doppler bank (1.4e-4 for a 0.5 s, 0.5–4 kHz sweep). So: solve once, predict every (array, event)
stretch, time again the events whose predicted stretch is on another row of the bank than the searched one,
and hand the re-timed features on (the estimate stage then solves them as usual).

Skipped (nothing computed): a source at rest (no Doppler bank in the frontend, no velocities). Arrays the
first solve calls unreliable keep their searched stretches (their geometry predicts nothing). A first solve
that fails or does not converge keeps the first pass's features.
"""
from __future__ import annotations

import time

import numpy as np


def retime_moving(session, feats, diag, progress=None):
    """(features, diagnostics) of ``extract_features`` on ``session`` re-timed with predicted stretches
    (module doc); the same objects when the source does not move. diagnostics ``retime``: the first solve's
    seconds, the events re-timed per array, the arrays skipped and why. progress : optional
    ``progress(done, total, message)``, told when the pass starts."""
    from calib.frontend import retime_arrivals

    if diag.get("_retime") is None:
        return feats, diag
    if progress is not None:
        n = len(session["arrays"])
        progress(n, n, "re-timing the moving source's arrivals")
    t0 = time.perf_counter()
    eps, record = first_pass_stretches(session, feats)
    record["solve_s"] = time.perf_counter() - t0
    if eps is None:   # the first pass's features stand (its re-timing state dropped)
        return feats, {**{k: v for k, v in diag.items() if k not in ("_retime", "_sweep_times")}, "retime": record}
    new, out = retime_arrivals(session, diag, eps)
    record["events"] = out.pop("retime")
    record["seconds"] = time.perf_counter() - t0
    return new, {**out, "retime": record}


FIRST_SOLVE_OUTLIERS = 20.0   # the first solve removes rows beyond this many σ (blunders, which bend the geometry),
# not the estimate's 5σ: that removal goes one row at a time, re-solving after each (2/3 of the solve's CPU on
# robot 44: 1.4 → 0.45 s), for error bars this pass does not use; it moved the predicted ε by ≤ 6e-6 (≤ 4 % of a
# bank step) on robot 44 and 0 … 3e-6 on four other moving scenes: 0-2 of ~300 events land on a neighbouring row


def first_solve(session, feats, outlier_threshold):
    """(solution, None) of the quick calibration a features stage may run on its own features (the stated
    sigmas, the linear clock: no noise re-estimation, no clock-model scans; ``outputs="solution"``), or
    (None, why) when it fails or does not converge. Used to predict a moving source's stretches and to refine
    a measured sample rate (pipeline/headerrate.py)."""
    from calib.estimator import ObservabilityError, calibrate

    from calib.pipeline.features import add_session_meta

    try:
        sol = calibrate(add_session_meta(feats, session, {}), outputs="solution", clock_model="linear",
                        noise="meta", outlier_threshold=outlier_threshold)
    except (ObservabilityError, ValueError) as exc:
        return None, f"first solve failed: {exc}"
    return (sol, None) if sol["converged"] else (None, "first solve did not converge")


def first_pass_stretches(session, feats):
    """({array: (K,) predicted ε per session event, NaN where none}, record) from a calibration of the
    first pass's features; (None, record with ``skipped``) when that solve cannot predict."""
    from calib.estimator.motion import predicted_stretches
    from calib.estimator.outputs import out_of_earshot

    # a geometry good to centimetres predicts the stretches (ε = ṙ/c) (robot 44: 3.3 → 1.4 s CPU, the stretches
    # within 2e-6; an array a clock fault bends is unreliable and keeps its searched stretches), and only
    # blunders removed as outliers (FIRST_SOLVE_OUTLIERS)
    sol, why = first_solve(session, feats, FIRST_SOLVE_OUTLIERS)
    if sol is None:
        return None, {"skipped": why}
    p, st = sol["problem"], sol["state"]
    eps = predicted_stretches(p, st, feats["events"], feats["meta"].get("stretch_time_s"))
    if eps is None:
        return None, {"skipped": "no source velocities"}
    ev_ids = session["events"]["event"].to_numpy(int)
    col = {int(e): k for k, e in enumerate(p.events)}
    unreliable = set(sol["unreliable_arrays"])
    # a diverged array (beyond earshot of every source) predicts nothing either
    unreliable |= {str(n) for n, far in zip(p.names, out_of_earshot(st.x, st.s)[0]) if far}
    out = {}
    for i, name in enumerate(p.names):
        if str(name) in unreliable:
            continue
        out[str(name)] = np.array([eps[i, col[int(e)]] if int(e) in col else np.nan for e in ev_ids])
    return out, {"unreliable_kept": sorted(unreliable)}
