"""How a moving source's TDOA rows err, and what their sigma says (issue 27): per `calib run` of a simulated session,
σ_TDOA as stated (meta ``sigma_tdoa``) split into the frontend's own noise figure and the shift model's part it
added (``frontend.extract.motion_sd``, recomputed), against the rows' actual errors at the simulator's truth.

    python benchmarks/diag_motion_sigma.py SESSION RUN [SESSION RUN ...]   # SESSION: `calib simulate`, RUN: `calib run`

At the true array poses, clocks and sources the rows of the estimator's final problem are evaluated with the
correction's own velocity (the odometry's Hermite curve at t* into the sweep, ``motion.sweep_middle``) and with
the true velocity error δv_j = v_true(t_j + t*) − v_hermite (truth/trajectory.csv, a cubic spline) as the
event-level nuisance (``State.dv``): ``total`` is the row error the solve sees without the nuisance, ``shared``
the part δv_j makes (the same for every array of event j: a source shift of β δv_j), ``indep`` what is left
(the rows' own noise and the shift model's error). Columns (µs, RMS over the rows): the stated σ, its noise and
motion parts, the three errors (TDOA-M's independent part also as its event-common part — the reference's
arrival, in every row of the event — and the median lag-1 correlation of an array's rows over events); then σ_v as ``motion.velocity_sigma`` states it against the true δv's RMS per
axis (m/s).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline


def true_velocity_error(session, p, t_star):
    """(K, 3) δv_j = the trajectory's true velocity at t_j + t* − the correction's (odometry Hermite curve)."""
    from calib.estimator.motion import source_velocities, sweep_middle

    tr = pd.read_csv(Path(session) / "truth" / "trajectory.csv")
    spl = CubicSpline(tr["t"].to_numpy(), tr[["x", "y", "z"]].to_numpy(), axis=0)
    ev = pd.read_csv(Path(session) / "events.csv").set_index("event").loc[np.asarray(p.events)].reset_index()
    vel, _ = source_velocities(ev, p.t, p.odom)
    v_h = sweep_middle(p.t, p.odom, vel, t_star)[1]
    return spl(ev["t_emit"].to_numpy(float) + t_star, 1) - v_h, vel   # (p.t: from the first emission)


def row_errors(p, st, kinds):
    """{kind: (m,) row error (s)} of the TDOA factors of ``p`` at ``st``."""
    from calib.estimator.factors import FACTORS
    from calib.estimator.problem import make_layout

    out = {}
    for k in ("tdoa_m", "tdoa_s"):
        if k in kinds:
            f = FACTORS[k](p, st, make_layout(p))
            out[k] = f.r * f.row_sigma
    return out


def motion_part(meta, run):
    """The shift model's part of σ_TDOA (s) that ``frontend.extract.motion_sd`` added (features do not record it:
    recomputed from events.csv, with the re-timed fraction when the run re-timed arrivals)."""
    from calib.frontend import extract

    diag = json.loads((Path(run) / "diagnostics" / "diagnostics.json").read_text())
    frac = extract.MOTION_MODEL_ERROR_RETIMED if diag.get("retime") else extract.MOTION_MODEL_ERROR
    ev = pd.read_csv(Path(run) / "features" / "events.csv")
    return extract.motion_sd(ev, meta["speed_of_sound"], meta["chirp_drift_bias"], frac)


def measure(session, run):
    import importlib
    cal = importlib.import_module("calib.estimator.calibrate")
    from calib.estimator.factors import active_kinds
    from calib.estimator.motion import velocity_sigma
    from calib.estimator.uncertainty import state_from_frames
    from calib.pipeline.formats.io import read_features, read_truth

    feat = read_features(Path(run) / "features")
    meta = feat["meta"]
    truth = read_truth(Path(session) / "truth")
    keep = cal.velocity_in_sigma
    cal.velocity_in_sigma = lambda m: False          # the nuisance in the problem: its State.dv can be set
    try:
        res = cal.calibrate(feat)
    finally:
        cal.velocity_in_sigma = keep
    p = res.problem
    if p.motion is None:
        return None
    t_star = float(meta.get("stretch_time_s") or meta.get("doa_time_s") or 0.0)
    dv, vel = true_velocity_error(session, p, t_star)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    st.e[:], st.odo_yaw[:] = 0.0, 0.0
    kinds = active_kinds(p)
    st.dv = np.zeros((p.K, 3))
    tot = row_errors(p, st, kinds)
    st.dv = dv
    ind = row_errors(p, st, kinds)
    sig = float(meta["sigma_tdoa"])
    mot = motion_part(meta, run)
    rec = {"session": Path(session).name, "sigma": sig, "motion_sd": mot,
           "noise": float(np.sqrt(max(sig ** 2 - mot ** 2, 0.0)))}
    for k in tot:
        rec[f"{k}_total"] = _rms(tot[k])
        rec[f"{k}_shared"] = _rms(tot[k] - ind[k])
        rec[f"{k}_indep"] = _rms(ind[k])
    rec["event_common"], rec["lag1"] = _structure(ind["tdoa_m"], p.tdoa_m.arr, p.tdoa_m.ev)
    rec["sigma_v"] = velocity_sigma(p.t, p.odom, vel, t_star, p.sigma["odometry"])
    rec["dv_rms_axis"] = float(np.sqrt(np.mean(dv ** 2)))
    return rec


def _structure(r, arr, ev):
    """(RMS over events of the event-mean of the TDOA-M errors ``r`` (s): the reference's arrival error, common to
    every row of its event; median over arrays of the lag-1 correlation of an array's errors in event order)."""
    evm = np.array([np.mean(r[ev == j]) for j in np.unique(ev)])
    lag = []
    for i in np.unique(arr):
        x = r[arr == i][np.argsort(ev[arr == i])]
        if len(x) > 3:
            lag.append(np.corrcoef(x[:-1] - np.median(x), x[1:] - np.median(x))[0, 1])
    return _rms(evm), float(np.median(lag)) if lag else float("nan")


def _rms(x):
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def main(argv=None):
    args = list(sys.argv[1:] if argv is None else argv)
    print("| session | σ_TDOA stated | its noise part | its motion part | TDOA-M total | shared (δv) | indep "
          "| TDOA-M indep: event-common | lag-1 | TDOA-S total | shared | indep | σ_v stated (m/s) "
          "| true δv RMS/axis (m/s) |")
    print("|---" * 14 + "|")
    for session, run in zip(args[::2], args[1::2]):
        r = measure(session, run)
        if r is None:
            print(f"| {Path(session).name} | no motion correction |")
            continue
        us = (lambda k: f"{1e6 * r.get(k, np.nan):.1f}")
        print(f"| {r['session']} | {us('sigma')} | {us('noise')} | {us('motion_sd')} | {us('tdoa_m_total')} "
              f"| {us('tdoa_m_shared')} | {us('tdoa_m_indep')} | {us('event_common')} | {r['lag1']:+.2f} | {us('tdoa_s_total')} | {us('tdoa_s_shared')} "
              f"| {us('tdoa_s_indep')} | {r['sigma_v']:.4f} | {r['dv_rms_axis']:.4f} |", flush=True)


if __name__ == "__main__":
    main()
