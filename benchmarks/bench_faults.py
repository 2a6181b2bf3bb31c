"""Fault-injection benchmark (issue 10): feature-level scenes with realistic faults, 10 seeds.

    python benchmarks/bench_faults.py                 # 10 seeds, all faults
    python benchmarks/bench_faults.py --seeds 3       # quick look

Scenes come from ``calib.pipeline.simulate.featsim.simulate_features`` (trajectories 1–3 by seed, σ_TDOA 0.1 ms,
σ_DOA 5°, σ_odo 3 cm). Faults, each injected into the same scene as the clean run:

- ``late``: 5 % of the arrivals (array, event) late by U(0.3, 40) ms (their TDOA-M and TDOA-S rows move)
  plus 5 % of the DOAs replaced, half by the direction of the source's mirror image in a wall, half by a
  random direction;
- ``array``: one non-reference array with all arrivals 1 ms late and every DOA pointing at the mirror
  image of the source in one wall (an occluded array hearing a reflection);
- ``odo_rot``: the odometry vectors rotated by +20° about the vertical (odometry frame ≠ reference frame;
  the estimated yaw, odometry → reference, is then −20°);
- ``t_emit``: emission times scaled by 1.5 (a wrong schedule);
- ``noisy``: one non-reference array with NOISY_FACTOR (3×) the TDOA and DOA noise of the others (not a
  fault to flag: a case for per-array variance components, ``--noise estimate --array-noise``).

    python benchmarks/bench_faults.py --faults noisy --noise estimate [--array-noise]

Prints per run: location error (mean over non-reference arrays, cm), orientation error (geodesic, deg),
verdict status, outliers, flagged arrays; then the acceptance checks of issue 10.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.estimator import calibrate
from calib.estimator.problem import build_problem
from calib.estimator.uncertainty import covariance, fisher, std_from_cov
from calib.pipeline.montecarlo import truth_state
from calib.pipeline.simulate.featsim import simulate_features

SIGMA_TDOA, SIGMA_DOA_DEG, SIGMA_ODO = 1e-4, 5.0, 0.03
LATE_FRACTION, LATE_RANGE_S = 0.05, (0.3e-3, 40e-3)
DOA_FRACTION = 0.05
ARRAY_DELAY_S = 1e-3
ODO_YAW_DEG = 20.0
T_EMIT_SCALE = 1.5
NOISY_FACTOR = 3.0


def _truth_pose(truth):
    a = truth["arrays"]
    R = Rotation.from_quat(a[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
    return a[["x", "y", "z"]].to_numpy(float), R


def _walls(truth, margin=1.0):
    """Six wall planes (point, normal) of a box around arrays and sources, ``margin`` m outside."""
    pts = np.vstack([truth["arrays"][["x", "y", "z"]].to_numpy(float), truth["sources"][["x", "y", "z"]].to_numpy(float)])
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    return [(np.where(np.arange(3) == k, b[k], 0.0), np.eye(3)[k]) for k in range(3) for b in (lo, hi)]


def _mirror(s, wall):
    p0, n = wall
    return s - 2.0 * ((s - p0) @ n)[:, None] * n


def _doa(truth, arr_idx, src):
    x, R = _truth_pose(truth)
    u = R[arr_idx].inv().apply(src - x[arr_idx])
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def delay_arrivals(feats, names, arrivals):
    """Add delays to arrivals {(array name, event): seconds} in TDOA-M and TDOA-S (the reference too)."""
    ref = feats["meta"]["reference_array"]
    tm, ts = feats["tdoa_m"].copy(), feats["tdoa_s"].copy()
    for (a, e), d in arrivals.items():
        if a == ref:
            tm.loc[tm.event == e, "tdoa"] -= d
        else:
            tm.loc[(tm.event == e) & (tm.array == a), "tdoa"] += d
        ts.loc[(ts.array == a) & (ts.to_event == e), "tdoa"] += d
        ts.loc[(ts.array == a) & (ts.from_event == e), "tdoa"] -= d
    return {**feats, "tdoa_m": tm, "tdoa_s": ts}


def fault_late(feats, truth, rng):
    names = feats["meta"]["arrays"]
    K = len(feats["events"])
    pairs = [(a, e) for a in names for e in range(K)]
    pick = rng.choice(len(pairs), max(1, int(round(LATE_FRACTION * len(pairs)))), replace=False)
    out = delay_arrivals(feats, names, {pairs[k]: rng.uniform(*LATE_RANGE_S) for k in pick})
    doa = feats["doa"].copy()
    rows = rng.choice(len(doa), max(2, int(round(DOA_FRACTION * len(doa)))), replace=False)
    walls = _walls(truth)
    src = truth["sources"][["x", "y", "z"]].to_numpy(float)
    for n, k in enumerate(rows):
        a = names.index(doa.at[k, "array"])
        e = int(doa.at[k, "event"])
        if n % 2 == 0:
            u = _doa(truth, [a], _mirror(src[[e]], walls[rng.integers(len(walls))]))[0]
        else:
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
        doa.loc[k, ["ux", "uy", "uz"]] = u
    out["doa"] = doa
    return out, None


def fault_array(feats, truth, rng):
    names = feats["meta"]["arrays"]
    bad = names[1 + rng.integers(len(names) - 1)]
    K = len(feats["events"])
    out = delay_arrivals(feats, names, {(bad, e): ARRAY_DELAY_S for e in range(K)})
    doa = feats["doa"].copy()
    walls = _walls(truth)
    wall = walls[rng.integers(len(walls))]
    src = truth["sources"][["x", "y", "z"]].to_numpy(float)
    m = (doa.array == bad).to_numpy()
    ev = doa.loc[m, "event"].to_numpy(int)
    doa.loc[m, ["ux", "uy", "uz"]] = _doa(truth, [names.index(bad)] * m.sum(), _mirror(src[ev], wall))
    out["doa"] = doa
    return out, bad


def fault_odo_rot(feats, truth, rng):
    ev = feats["events"].copy()
    o = ev[["odom_x", "odom_y", "odom_z"]].to_numpy(float).copy()
    ev[["odom_x", "odom_y", "odom_z"]] = Rotation.from_euler("z", ODO_YAW_DEG, degrees=True).apply(o)
    return {**feats, "events": ev}, None


def fault_t_emit(feats, truth, rng):
    ev = feats["events"].copy()
    ev["t_emit"] = ev["t_emit"] * T_EMIT_SCALE
    return {**feats, "events": ev}, None


def fault_noisy(feats, truth, rng):
    """One non-reference array with NOISY_FACTOR × the scene's TDOA and DOA noise (extra independent noise
    of the featsim model on each of its rows)."""
    names = feats["meta"]["arrays"]
    bad = names[1 + rng.integers(len(names) - 1)]
    extra = np.sqrt(NOISY_FACTOR ** 2 - 1.0)
    out = dict(feats)
    for key, col in (("tdoa_m", "array"), ("tdoa_s", "array")):
        t = feats[key].copy()
        m = (t[col] == bad).to_numpy()
        t.loc[m, "tdoa"] += rng.normal(0.0, extra * SIGMA_TDOA, m.sum())
        out[key] = t
    doa = feats["doa"].copy()
    m = (doa.array == bad).to_numpy()
    axis = rng.normal(size=(m.sum(), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    turn = Rotation.from_rotvec(axis * np.deg2rad(rng.normal(0.0, extra * SIGMA_DOA_DEG, (m.sum(), 1))))
    doa.loc[m, ["ux", "uy", "uz"]] = turn.apply(doa.loc[m, ["ux", "uy", "uz"]].to_numpy(float).copy())
    out["doa"] = doa
    return out, bad


FAULTS = {"late": fault_late, "array": fault_array, "odo_rot": fault_odo_rot, "t_emit": fault_t_emit,
          "noisy": fault_noisy}
# faults whose array is still calibrated (its error shown apart), not one to flag
KEEP_BAD = ("noisy",)


def errors(cal, truth, skip=None):
    """Mean position error (m) and geodesic orientation error (deg) over non-reference arrays (not ``skip``)."""
    x, R = _truth_pose(truth)
    e = cal["arrays"]
    xe = e[["x", "y", "z"]].to_numpy(float)
    Re = Rotation.from_quat(e[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
    names = list(e["array"])
    keep = [k for k in range(1, len(names)) if names[k] != skip]
    loc = np.linalg.norm(xe[keep] - x[keep], axis=1).mean()
    ang = np.rad2deg((Re[keep] * R[keep].inv()).magnitude()).mean()
    return loc, ang


def yaw_crlb(feats, truth):
    """What estimating the odometry yaw costs, by the CRLB at ground truth: (yaw 1-σ in deg, mean 3-D
    position bound of the non-reference arrays with the yaw free, the same with the yaw known) in m.
    The yaw's only information is the reference array's DOAs against the odometry's directions."""
    p = build_problem(feats, odometry_yaw=True)
    st = truth_state(p, truth)
    out = []
    for free in (True, False):
        p = p.replace(odo_yaw_free=free)
        J, lay = fisher(p, st)
        cov = covariance(J, lay.n, lay)
        sd = std_from_cov(p, lay, cov)["x"][1:]
        out.append(float(np.mean(np.linalg.norm(sd, axis=1))))
        if free:
            yaw_sd = float(np.rad2deg(np.sqrt(cov[lay.odo_yaw[0], lay.odo_yaw[0]])))
    return yaw_sd, out[0], out[1]


def _array_error(cal, truth, k):
    """Position error (m) of array k."""
    x, _ = _truth_pose(truth)
    return float(np.linalg.norm(cal["arrays"][["x", "y", "z"]].to_numpy(float)[k] - x[k]))


def _verdict(cal):
    """The calibration's verdict (a version without one — the baseline — counts as "ok" with exit 0)."""
    return cal["report"].get("verdict") or {"status": "ok (no verdict)", "reasons": [], "flagged_arrays": []}


def one(seed, faults, options=None):
    traj = 1 + seed % 3
    feats, truth = simulate_features(traj, SIGMA_TDOA, SIGMA_DOA_DEG, SIGMA_ODO, seed=1000 + seed)
    rows = []
    t0 = time.perf_counter()
    options = options or {}
    clean = calibrate(feats, **options)
    base = {"seed": seed, "traj": traj}
    cl, ca = errors(clean, truth)
    rows.append({**base, "fault": "clean", "loc_cm": 100 * cl, "ang_deg": ca, "status": _verdict(clean)["status"],
                 "outliers": len(clean["report"]["outliers"]), "flagged": "", "bad": "",
                 "seconds": time.perf_counter() - t0, "clean_loc_cm": 100 * cl, "clean_ang_deg": ca})
    for name in faults:
        rng = np.random.default_rng(seed)
        f2, bad = FAULTS[name](feats, truth, rng)
        t0 = time.perf_counter()
        try:
            cal = calibrate(f2, **options)
        except ValueError as exc:   # refused (observability): counts as not ok
            rows.append({**base, "fault": name, "status": f"refused: {exc}", "seconds": time.perf_counter() - t0})
            continue
        rep = cal["report"]
        loc, ang = errors(cal, truth, skip=bad)
        cl_o, ca_o = errors(clean, truth, skip=bad)
        v = _verdict(cal)
        row = {**base, "fault": name, "loc_cm": 100 * loc, "ang_deg": ang, "status": v["status"],
               "outliers": len(rep["outliers"]), "flagged": ",".join(v["flagged_arrays"]),
               "bad": bad or "", "seconds": time.perf_counter() - t0, "clean_loc_cm": 100 * cl_o,
               "clean_ang_deg": ca_o, "reasons": "; ".join(v["reasons"])}
        if "odometry_yaw_deg" in rep:
            row["yaw_deg"] = rep["odometry_yaw_deg"]
            row["yaw_std_deg"] = rep.get("odometry_frame", {}).get("yaw_std_deg")
        if name in KEEP_BAD:
            names = list(cal["arrays"]["array"])
            row["bad_loc_cm"] = 100 * _array_error(cal, truth, names.index(bad))
            row["bad_clean_loc_cm"] = 100 * _array_error(clean, truth, names.index(bad))
            row["bad_factor"] = {k: v.get(bad) for k, v in rep["sigmas"].get("per_array_factor", {}).items()}
        if name == "odo_rot":
            row["crlb_yaw_deg"], row["crlb_loc_free_cm"], row["crlb_loc_fixed_cm"] = (
                v * f for v, f in zip(yaw_crlb(feats, truth), (1, 100, 100)))
        rows.append(row)
    return rows


def acceptance(df):
    """The issue-10 checks as lines of text."""
    out = []
    g = df[df.fault == "late"]
    if len(g):
        ok = (g.loc_cm <= 1.5 * g.clean_loc_cm + 1.0) & (g.ang_deg <= 1.5 * g.clean_ang_deg + 0.5)
        out.append(f"late arrivals + bad DOAs: within 1.5x clean (+1 cm/+0.5 deg) in {ok.sum()}/{len(g)} runs")
    g = df[df.fault == "array"]
    if len(g):
        named = sum(b in str(f).split(",") for b, f in zip(g.bad, g.flagged))
        ok = (g.loc_cm <= 1.5 * g.clean_loc_cm) & (g.ang_deg <= 1.5 * g.clean_ang_deg)
        out.append(f"bad array named in flagged_arrays in {named}/{len(g)} runs (>= 9/10); others within 1.5x "
                   f"clean in {ok.sum()}/{len(g)}")
    g = df[df.fault == "odo_rot"]
    if len(g):
        ok = g.loc_cm <= 1.2 * g.clean_loc_cm
        yaw = (np.abs(g["yaw_deg"] + ODO_YAW_DEG) <= 1.0).sum() if "yaw_deg" in g else 0
        out.append(f"odometry rotated {ODO_YAW_DEG:g} deg: within 1.2x aligned in {ok.sum()}/{len(g)} runs; "
                   f"yaw within 1 deg in {yaw}/{len(g)}")
        if "crlb_yaw_deg" in g:
            out.extend(_yaw_bound_lines(g))
    g = df[df.fault == "noisy"]
    if len(g):
        out.append(f"one array with {NOISY_FACTOR:g}x the noise: other arrays {g.loc_cm.mean():.2f} cm / "
                   f"{g.ang_deg.mean():.2f} deg (same scene without it: {g.clean_loc_cm.mean():.2f} cm / "
                   f"{g.clean_ang_deg.mean():.2f} deg); the noisy array {g.bad_loc_cm.mean():.2f} cm "
                   f"(without the extra noise {g.bad_clean_loc_cm.mean():.2f} cm)")
    g = df[df.fault == "t_emit"]
    if len(g):
        out.append(f"t_emit x{T_EMIT_SCALE:g}: ends failed (or refused) in "
                   f"{g.status.astype(str).str.match('failed|refused').sum()}/{len(g)} runs")
    bad = df[(df.fault != "clean") & (df.loc_cm > 2 * df.clean_loc_cm + 2.0)]
    out.append(f"runs with location error > 2x clean + 2 cm: {len(bad)}, of which ending ok: "
               f"{bad.status.astype(str).str.startswith('ok').sum()} (target 0)")
    return out


def _yaw_bound_lines(g):
    """The odometry-yaw runs against the CRLB: how many 'within 1 deg' an efficient estimator would give,
    the bound's cost of a free yaw on the array positions, and the yaw errors in units of the reported σ."""
    from scipy.stats import chi2, norm
    expect = float(np.sum(2 * norm.cdf(1.0 / g.crlb_yaw_deg) - 1))
    ratio = g.crlb_loc_free_cm / g.crlb_loc_fixed_cm
    z = (g.yaw_deg + ODO_YAW_DEG) / g.yaw_std_deg
    # with a right sigma the RMS of n z's is √(χ²_n / n): over 2 runs anything in 0.16-1.92 (the 1.66 of seeds
    # 430-431 was one z of 2.2; 100 runs, seeds 500-599: RMS 1.00, the sigma equal to the CRLB at the truth)
    lo, hi = (np.sqrt(chi2.ppf(q, len(z)) / len(z)) for q in (0.025, 0.975))
    return [f"  CRLB of the yaw {g.crlb_yaw_deg.min():.2f}-{g.crlb_yaw_deg.max():.2f} deg: an efficient estimator "
            f"is within 1 deg in {expect:.1f}/{len(g)} runs on average",
            f"  CRLB of the array positions, yaw free / yaw known: {g.crlb_loc_free_cm.mean():.2f} / "
            f"{g.crlb_loc_fixed_cm.mean():.2f} cm (ratio {ratio.min():.2f}-{ratio.max():.2f}, mean {ratio.mean():.2f})",
            f"  yaw error / reported sigma: RMS {np.sqrt(np.mean(z ** 2)):.2f} over {len(z)} runs (a right sigma gives "
            f"{lo:.2f}-{hi:.2f}, 95 %), max |z| {np.abs(z).max():.2f}; reported sigma / CRLB "
            f"{np.mean(g.yaw_std_deg / g.crlb_yaw_deg):.2f}"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed … first-seed + seeds - 1 (new seeds: "
                    "a check on scenes nothing was tuned on)")
    ap.add_argument("--faults", default=",".join(FAULTS))
    ap.add_argument("--csv")
    ap.add_argument("--noise", default="auto", choices=("auto", "meta", "estimate"), help="calibrate(noise=...)")
    ap.add_argument("--array-noise", action="store_true", help="per-array variance components (with --noise estimate)")
    args = ap.parse_args()
    faults = [f for f in args.faults.split(",") if f]
    options = {"noise": args.noise, "array_noise": args.array_noise}
    rows = [r for s in range(args.first_seed, args.first_seed + args.seeds) for r in one(s, faults, options)]
    df = pd.DataFrame(rows)
    if args.csv:
        df.to_csv(args.csv, index=False)
    pd.set_option("display.width", 220)
    pd.set_option("display.max_colwidth", 60)
    cols = [c for c in ("seed", "traj", "fault", "loc_cm", "clean_loc_cm", "ang_deg", "clean_ang_deg", "yaw_deg", "yaw_std_deg",
                        "crlb_yaw_deg",
                        "status", "outliers", "bad", "flagged", "bad_loc_cm", "bad_factor", "seconds") if c in df]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print()
    print("\n".join(acceptance(df)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
