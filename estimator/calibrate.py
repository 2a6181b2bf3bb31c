"""The estimator: initialise → IVE (paper's stage 1) → joint robust NLS → outlier removal → final NLS.

``calibrate(features) -> calibration dict`` is the library entry point; see :func:`calibrate`.
"""
from __future__ import annotations

import time

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController

from calib import __version__

from .factors import ALL_KINDS, UNITS
from .init import ObservabilityError, doa_rotation, initialise, kabsch, reflect, subproblem
from .observability import check_observability
from .problem import build_problem, copy_state, make_layout
from .solver import levenberg_marquardt, linearise
from .uncertainty import covariance, std_from_cov



# The matrices here are tiny (~400 × 100): multi-threaded BLAS only adds synchronisation (measured 4×
# slower on 2 cores), so the estimator runs BLAS single-threaded and parallelism goes across calibrations.
_BLAS = ThreadpoolController()




def rotations_by_kabsch(p, st):
    """Each non-reference array's rotation by SVD alignment of DOA-scaled points (the paper's IVE step)."""
    for i in range(p["N"]):
        m = p["doa_arr"] == i
        if i == p["ref"] or m.sum() < 2:
            continue
        j = p["doa_ev"][m]
        w = st["s"][j] - st["x"][i]
        d = np.linalg.norm(w, axis=1, keepdims=True)
        u = p["doa_u"][m]
        n = p["fold"][i]
        if np.any(n):
            # mirror-ambiguous DOAs: decide which events lie behind the mic plane afresh from the IVE's
            # positions and sources, which no longer depend on this array's DOAs
            u = np.where(((w @ doa_rotation(p, st, i, st["x"][i])) @ n < 0)[:, None], reflect(u, n), u)
        st["R"][i], _ = kabsch(u * d, w)
    return st


def residual_table(fs, mask=None):
    """Per measurement type: count, RMS in natural units (µs, deg, cm)."""
    out = {}
    for f in fs:
        if len(f["r"]) == 0:
            continue
        keep = mask[f["kind"]] if mask and f["kind"] in mask else np.ones(len(f["r"]), bool)
        r = f["r"][keep] * f["sigma"]
        if f["dim"] == 3:
            r = np.linalg.norm(r.reshape(-1, 3), axis=1)
        unit, scale = UNITS[f["kind"]]
        out[f["kind"]] = {"n": int(len(r)), f"rms_{unit}": float(np.sqrt(np.mean(r * r)) * scale) if len(r) else 0.0}
    return out


def to_frames(p, st, std=None):
    """State (+ std) → arrays and sources DataFrames of FORMATS.md section 3."""
    q = Rotation.from_matrix(st["R"]).as_quat(scalar_first=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    arrays = pd.DataFrame({"array": list(p["names"]), "x": st["x"][:, 0], "y": st["x"][:, 1], "z": st["x"][:, 2],
                           "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
                           "offset": st["offset"], "drift": st["drift"]})
    sources = pd.DataFrame({"event": p["events"], "x": st["s"][:, 0], "y": st["s"][:, 1], "z": st["s"][:, 2]})
    if std is not None:
        for k, c in enumerate("xyz"):
            arrays[f"{c}_std"] = std["x"][:, k]
        for k, c in enumerate("xyz"):
            arrays[f"r{c}_std"] = std["rot"][:, k]
        arrays["offset_std"] = std["offset"]
        arrays["drift_std"] = std["drift"]
        for k, c in enumerate("xyz"):
            sources[f"{c}_std"] = std["s"][:, k]
    return arrays, sources


def _outlier_mask(fs, threshold):
    """Boolean keep-masks for the robust factors: drop |r| beyond ``threshold`` robust scales."""
    mask, flagged = {}, []
    for f in fs:
        if not f["robust"] or len(f["r"]) == 0:
            continue
        r = f["r"]
        mad = 1.4826 * np.median(np.abs(r))
        scale = max(1.0, mad)  # never tighter than the stated sigma
        keep = np.abs(r) <= threshold * scale
        mask[f["kind"]] = keep
        for k in np.flatnonzero(~keep):
            flagged.append({"type": f["kind"], "line": int(f["row"][k]), "residual_sigma": float(r[k]),
                            "residual_us": float(r[k] * f["sigma"] * 1e6)})
    return mask, flagged


def solve_from(p, st, *, kinds, loss="cauchy", robust_k=3.0, outlier_threshold=5.0, max_iter=200):
    """Joint NLS from a given state: robust pass → outlier mask → plain least squares. Returns (state, info)."""
    lay = make_layout(p)
    info = {}
    # the robust pass only has to find the basin and the outliers; the final pass converges tightly
    st, info["robust"] = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, max_iter=max_iter,
                                             rtol=1e-6)
    _, _, _, _, fs = linearise(p, st, lay, kinds)
    mask, flagged = _outlier_mask(fs, outlier_threshold) if loss else ({}, [])
    st, info["final"] = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
    info["mask"], info["outliers"], info["layout"] = mask, flagged, lay
    return st, info


SIGMA_KEY = {"tdoa_s": "sigma_tdoa_s", "tdoa_m": "sigma_tdoa_m", "doa": "sigma_doa", "odometry": "sigma_odo"}


def estimate_noise(p, st, kinds, mask, *, iterations=1, min_redundancy=5.0, max_iter=200):
    """Re-estimate each measurement type's sigma from its residuals (variance-component estimation).

    σ_k² ← σ_k² · Σ_k r² / Σ_k (1 − h_ii), h the hat matrix of the whitened Jacobian, then re-solve;
    types with redundancy below ``min_redundancy`` keep their sigma, and a factor is clipped to 1e-4..1e4.
    One step by default: iterating lets a type that the parameters can absorb (e.g. TDOAs with few arrays
    and free sources) shrink without bound. Returns (state, p with new sigmas, info with the scales).
    """
    p = dict(p)
    lay = make_layout(p)
    scales = {k: 1.0 for k in SIGMA_KEY}
    info = {}
    for _ in range(iterations):
        r, J, w, _, fs = linearise(p, st, lay, kinds, mask=mask, dense=True)
        keep = w > 0
        Jk = J[keep]
        d = np.linalg.norm(Jk, axis=0)
        d = np.where(d > 0, d, 1.0)
        A = np.linalg.pinv((Jk / d).T @ (Jk / d))
        h = np.zeros(len(r))
        h[keep] = np.einsum("ij,jk,ik->i", Jk / d, A, Jk / d)
        start = 0
        changed = False
        for f in fs:
            n = len(f["r"])
            sl = slice(start, start + n)
            start += n
            key = SIGMA_KEY.get(f["kind"])
            if key is None or n == 0:
                continue
            red = float(np.sum((1.0 - h[sl])[keep[sl]]))
            if f["dim"] == 3 and f["kind"] == "doa":
                red -= n / 3.0  # a unit-vector residual has no noise along the direction itself
            if red < min_redundancy:
                continue
            factor = float(np.sum(r[sl][keep[sl]] ** 2)) / red
            factor = float(np.clip(factor, 1e-4, 1e4))
            p[key] *= np.sqrt(factor)
            scales[f["kind"]] *= np.sqrt(factor)
            changed |= abs(np.sqrt(factor) - 1.0) > 0.01
        st, info = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
        if not changed:
            break
    return st, p, {"scale": scales, **info}


def calibrate(features, **options):
    """Calibrate arrays (positions, rotations, offsets, drifts) and sources from a features dict.

    See :func:`calibrate_features` for the options; this wrapper only pins BLAS to one thread.
    """
    with _BLAS.limit(limits=1, user_api="blas"):
        return calibrate_features(features, **options)


def calibrate_features(features, *, method="hybrid", use_tdoa_s=True, emission_sigma=0.0, loss="cauchy", robust_k=3.0,
              outlier_threshold=5.0, max_iter=200, init_state=None, noise="auto"):
    """Calibrate arrays (positions, rotations, offsets, drifts) and sources from a features dict.

    Parameters
    ----------
    features : dict from ``pipeline.io.read_features`` (or a simulator).
    method : "hybrid" (this project's estimator, Zhang et al. structure) or "wang" (the baseline; see
        ``estimator.wang``).
    use_tdoa_s : use TDOA-S measurements (False gives Wang et al.'s setting with our solver).
    emission_sigma : prior std (s) of per-interval emission-time errors; 0 disables the correction.
    loss : robust loss on TDOA residuals for the first joint pass ("cauchy", "huber" or None).
    robust_k : robust scale, in units of the TDOA sigma.
    outlier_threshold : TDOA residuals beyond this many (robust) sigmas are flagged and excluded.
    init_state : optional state to start the joint solve from (skips initialisation; used to compare
        with a solve started from ground truth).
    noise : "meta" weights with the sigmas of meta.json (documented defaults when absent); "estimate"
        then re-estimates one sigma per measurement type from the residuals (variance components) and
        re-solves, so weights and error bars follow the data's actual noise; "auto" (default) estimates
        when meta.json says its sigmas are a frontend's own figures (``sigmas_estimated``), else "meta".

    Returns
    -------
    dict with ``arrays`` and ``sources`` DataFrames (with ``*_std`` columns: 1-σ from (JᵀWJ)⁻¹, rotation
    std per axis of the array frame in rad) and ``report`` (dict, see docs/method.md).
    """
    times = {}
    t0 = time.perf_counter()
    if method == "wang":
        from .wang import wang_initialise

        use_tdoa_s = False
    p = build_problem(features, use_tdoa_s=use_tdoa_s, sigma_emit=emission_sigma)
    if p["K"] < 3:
        raise ObservabilityError(f"only {p['K']} event(s): at least 3 are needed to calibrate")
    kinds = [k for k in ALL_KINDS if k != "emission" or emission_sigma > 0]
    stages, stage_states = {}, {}
    if init_state is None:
        if method == "wang":
            st, init_info = wang_initialise(p)
        else:
            st, init_info = initialise(p)
        times["init"] = time.perf_counter() - t0
        lay_full = make_layout(p)
        t_obs = time.perf_counter()
        check_observability(p, lay_full, kinds, st)
        times["observability"] = time.perf_counter() - t_obs
        stages["init"] = {"cost": float(linearise(p, st, lay_full, kinds)[3]), **_jsonable(init_info)}
        stage_states["init"] = copy_state(st)
        if method == "hybrid" and len(p["ts_val"]) > 0:
            # Stage 1 (IVE): positions, clocks and sources from hybrid TDOA, odometry and the reference
            # array's DOAs; then rotations by SVD alignment of DOA-scaled points.
            t1 = time.perf_counter()
            q = subproblem(p, np.arange(p["N"]), doa_arrays=[p["ref"]])
            lay_ive = make_layout(q, rotations=False)
            st, ive = levenberg_marquardt(q, st, lay_ive, ["tdoa_s", "tdoa_m", "doa", "odometry"], loss=loss,
                                          k=robust_k, max_iter=max_iter, rtol=1e-6)
            st = rotations_by_kabsch(p, st)
            stage_states["ive"] = copy_state(st)
            stages["ive"] = {"cost": ive["cost"], "iterations": ive["iterations"], "reason": ive["reason"]}
            times["ive"] = time.perf_counter() - t1
    else:
        st = {k: np.array(v, dtype=float, copy=True) for k, v in init_state.items()}
    t2 = time.perf_counter()
    st, info = solve_from(p, st, kinds=kinds, loss=loss, robust_k=robust_k, outlier_threshold=outlier_threshold,
                          max_iter=max_iter)
    if noise == "auto":
        noise = "estimate" if features["meta"].get("sigmas_estimated") else "meta"
    if noise == "estimate":
        st, p, vce = estimate_noise(p, st, kinds, info["mask"], max_iter=max_iter)
        info["final"] = {**info["final"], **{k: vce[k] for k in ("iterations", "cost", "converged", "reason")}}
        stages["noise"] = {"scale": vce["scale"]}
    elif noise != "meta":
        raise ValueError(f"noise must be 'auto', 'meta' or 'estimate', not {noise!r}")
    times["joint"] = time.perf_counter() - t2
    lay = info["layout"]
    r, J, w, cost, fs = linearise(p, st, lay, kinds, mask=info["mask"])
    J = J[w > 0]
    t_cov = time.perf_counter()
    cov = covariance(J, lay["n"], lay)
    times["uncertainty"] = time.perf_counter() - t_cov
    std = std_from_cov(p, lay, cov)
    arrays, sources = to_frames(p, st, std)
    times["total"] = time.perf_counter() - t0
    n_res = int(J.shape[0])
    report = {
        "software": {"name": "calib", "version": __version__},
        "method": method,
        "converged": bool(info["final"]["converged"]),
        "reason": info["final"]["reason"],
        "iterations": {"robust": info["robust"]["iterations"], "final": info["final"]["iterations"]},
        "cost": {**{k: v["cost"] for k, v in stages.items() if "cost" in v}, "joint_robust": info["robust"]["cost"],
                 "final": cost},
        "stages": stages,
        "chi2_per_dof": float(2 * cost / max(n_res - lay["n"], 1)),
        "residuals": residual_table(fs, info["mask"]),
        "outliers": info["outliers"],
        "used": {"tdoa_s": bool(len(p["ts_val"])), "tdoa_m": bool(len(p["tm_val"])), "doa": bool(len(p["doa_u"])),
                 "emission_correction": emission_sigma > 0},
        "drift_reference": "emitter clock" if len(p["ts_val"]) else "reference array (no TDOA-S: its drift fixed to 0)",
        "sigmas": {"tdoa_s": p["sigma_tdoa_s"], "tdoa_m": p["sigma_tdoa_m"], "doa_rad_per_axis": p["sigma_doa"],
                   "odometry_m": p["sigma_odo"], "emission_s": emission_sigma, "source": noise},
        "timings_s": times,
    }
    if emission_sigma > 0:
        report["emission_corrections_s"] = {int(e): float(v) for e, v in zip(p["events"], st["e"])}
    return {"arrays": arrays, "sources": sources, "report": report, "state": st, "problem": p,
            "stage_states": stage_states}


def _jsonable(d):
    return {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in d.items()
            if isinstance(v, (int, float, str, np.floating, dict))}
