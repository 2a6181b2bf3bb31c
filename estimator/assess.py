"""A calibration read back from disk, evaluated against its features: residuals per measurement type
and position covariances. The public API the report (and a notebook) uses; no estimator internals leak.

``model = rebuild(features, calibration)``; ``residuals(model)``; ``position_covariances(model)``.
"""
from __future__ import annotations

import numpy as np

from calib.blas import single_thread_blas
from calib.tables import ARRAY_PARAMS, array_param

from . import clockmodel
from .factors import KINDS, active_kinds, natural
from .factors import evaluate as factors
from .observability import check_observability
from .problem import build_problem, make_layout, with_arrival_scale
from .screen import without_screened
from .solver import linearise
from .uncertainty import cov_block, honest_covariance, plane_normals, state_from_frames


def rebuild(features, calib):
    """The estimator's problem, state, layout, factor kinds and outlier mask at a calibration read from disk.

    Returns None when the calibration cannot be evaluated against these features (no sources.csv,
    arrays/events that do not match, or positions left unknown: a diverged solve's, ``outputs.blank_diverged``).
    """
    rep = calib.get("report") or {}
    src = calib.get("sources")
    names = set(features["meta"]["arrays"])
    if src is None or set(calib["arrays"]["array"]) != names or \
            set(src["event"]) != set(features["events"]["event"]) or \
            not all(np.isfinite(t[["x", "y", "z"]].to_numpy(float)).all() for t in (calib["arrays"], src)):
        return None
    sig_e = float((rep.get("sigmas") or {}).get("emission_s") or 0.0)
    use_ts = bool((rep.get("used") or {}).get("tdoa_s", True))
    frame = rep.get("odometry_frame") or {}
    # the rows it solved with (the screened ones out) and the clock models it chose (steps, drift terms): taken out
    # of the TDOAs as it did
    features = clockmodel.correct_features(without_screened(features, rep.get("screened")),
                                           clockmodel.models_from_report(rep))
    p = build_problem(features, use_tdoa_s=use_ts, sigma_emit=sig_e, odometry_yaw=bool(frame.get("estimated")))
    # the weights the estimator ended with (meta.json's, or re-estimated from the residuals: noise="estimate")
    sigmas = rep.get("sigmas") or {}
    stated = {kind.name: sigmas.get(kind.report_sigma) for kind in KINDS.values() if kind.reweight}
    sigma = {k: float(v) for k, v in stated.items() if isinstance(v, (int, float)) and v > 0}
    # ... and the arrays' own components (array_noise=True: report.json lists the arrays whose one moved)
    p = p.replace(sigma={**p.sigma, **sigma}, array_scale={
        kind: np.array([float(own.get(str(n), 1.0)) for n in p.names])
        for kind, own in (sigmas.get("per_array_factor") or {}).items() if own})
    # ... and the arrays' arrival scales (meta sigma_arrival_per_array, moved by the residuals: report.json)
    if sigmas.get("arrival_scale"):
        p = with_arrival_scale(p, [float(sigmas["arrival_scale"].get(str(n), 1.0)) for n in p.names])
    st = state_from_frames(p, calib["arrays"], src)
    corr = rep.get("emission_corrections_s") or {}
    st.e = np.array([float(corr.get(str(e), corr.get(e, 0.0)) or 0.0) for e in p.events])
    st.odo_yaw = np.array([np.deg2rad(float(frame.get("yaw_deg") or 0.0))])
    p, st = _solved_speed(p, st, rep.get("speed_of_sound"))
    kinds = active_kinds(p)
    if _rank_deficient(p, rep.get("undetermined") or []):
        # the estimator left out what the data do not determine: the same rank check at the estimate
        p = check_observability(p, make_layout(p), kinds, st)
    lay = make_layout(p)
    mask = outlier_mask(p, st, lay, kinds, rep.get("outliers"))
    return {"problem": p, "state": st, "layout": lay, "kinds": kinds, "mask": mask,
            "shared": bool(features["meta"].get("tdoa_shared_arrivals")),
            "normals": plane_normals(features["meta"], p.names)}


def _solved_speed(p, st, speed):
    """(problem, state) with the speed of sound the estimator solved (report.json ``speed_of_sound``, when
    ``estimated``): free with its prior, at its value (``State.cs``); as they are otherwise."""
    if not (speed or {}).get("estimated"):
        return p, st
    test = speed.get("test") or {}
    p = p.replace(c_free=True, c_test=test or None,
                  sigma={**p.sigma, "speed": float(test.get("prior_relative") or 0.0)})
    st.cs = np.array([np.log(float(speed["value_m_s"]) / p.c)])
    return p, st


def outlier_mask(p, st, lay, kinds, outliers):
    """{kind: (residuals,) bool} with the rows of report.json ``outliers`` (their type and CSV line) left out."""
    flagged = {}
    for o in outliers or []:
        flagged.setdefault(o["type"], set()).add(int(o["line"]))
    return {f.kind: ~np.isin(f.row, list(flagged[f.kind])) for f in factors(p, st, lay, kinds) if f.kind in flagged}


def _rank_deficient(p, undetermined):
    """True when report.json ``undetermined`` names parameters found by the rank check (not the roll of a
    linear array, not the orientation of an array without DOAs for 2 events)."""
    index = {str(n): i for i, n in enumerate(p.names)}
    for u in undetermined:
        i = index.get(u.get("array"))
        if i is None or u.get("parameter") == "roll":
            continue
        if u.get("parameter") != "orientation" or p.rot_free[i]:
            return True
    return False


def _undetermined(p):
    """{(array index, layout key)} of the parameters the rank check left out (``p.unobservable``)."""
    index = {str(n): i for i, n in enumerate(p.names)}
    return {(index[u["array"]], array_param(u["parameter"]).key) for u in p.unobservable}


def residuals(model):
    """Residuals per measurement type in natural units.

    Returns {kind: {"values": (m,) µs / deg / cm, "outlier": (m,) bool, "sigma": the type's 1-σ
    (report.json "sigmas"), same unit, "row_sigma": (m,) the 1-σ each value was weighted with (the type's
    times its row's scale: doa.csv ``sigma_deg``, per-array variance components), "dist": "normal" |
    "rayleigh", "unit": str}}. DOA values are angles between the measured and the predicted direction
    (Rayleigh with the per-axis σ); odometry values are per axis.
    """
    out = {}
    for f in factors(model["problem"], model["state"], model["layout"], model["kinds"]):
        if len(f.r) == 0:
            continue
        unit, scale = KINDS[f.kind].unit, KINDS[f.kind].scale
        keep = model["mask"].get(f.kind, np.ones(len(f.r), bool))
        r = natural(f)
        if f.kind == "doa":
            d = np.linalg.norm(r.reshape(-1, 3), axis=1)  # |v − u| = 2 sin(θ/2)
            vals = np.rad2deg(2 * np.arcsin(np.clip(d / 2, 0, 1)))
            keep = keep.reshape(-1, 3).all(axis=1)
            # per tangent axis σ → the angle is Rayleigh(σ); shown with its scale
            row_sigma = np.broadcast_to(f.row_sigma, len(f.r)).reshape(-1, 3)[:, 0]
            out["doa"] = {"values": vals, "outlier": ~keep, "sigma": np.rad2deg(f.sigma),
                          "row_sigma": np.rad2deg(row_sigma), "dist": "rayleigh", "unit": "deg"}
            continue
        out[f.kind] = {"values": r * scale, "outlier": ~keep, "sigma": f.sigma * scale,
                       "row_sigma": np.broadcast_to(f.row_sigma, len(f.r)) * scale, "dist": "normal",
                       "unit": unit.replace("us", "µs")}
    return out


def position_covariances(model):
    """1-σ position covariances at the estimate: arrays (N, 3, 3) and sources (K, 3, 3), m² (NaN where fixed)."""
    p, lay = model["problem"], model["layout"]
    lin = linearise(p, model["state"], lay, model["kinds"], mask=model["mask"])
    with single_thread_blas():   # (calib.blas)
        cov = honest_covariance(p, lin, lay, shared=model.get("shared", False), normals=model.get("normals"),
                                state=model["state"])

    def blocks(idx, skip=()):
        out = np.full((len(idx), 3, 3), np.nan)
        for k, ix in enumerate(idx):
            if np.all(ix >= 0) and k not in skip:
                out[k] = cov_block(cov, ix)
        return out

    return blocks(lay.x, {i for i, key in _undetermined(p) if key == "x"}), blocks(lay.s)


def array_covariance(model):
    """Full 1-σ covariance of the free array parameters at the estimate (the ``*_std`` columns' covariance:
    ``uncertainty.honest_covariance``), of a calibration rebuilt from disk (:func:`rebuild`). ``calibrate``'s
    own result carries it (``CalibrationResult.array_covariance``), computed once with its std columns.

    Returns (labels, cov): as :func:`labelled_array_covariance`.
    """
    p, lay = model["problem"], model["layout"]
    lin = linearise(p, model["state"], lay, model["kinds"], mask=model["mask"])
    with single_thread_blas():   # small dense blocks (calib.blas): threads only add synchronisation
        # large problems: the array block alone
        cov = honest_covariance(p, lin, lay, shared=model.get("shared", False), normals=model.get("normals"),
                                arrays_only=True, state=model["state"])
    return labelled_array_covariance(p, lay, cov)


def labelled_array_covariance(p, lay, cov, without=()):
    """(labels, cov) of the free array parameters from a covariance of the layout ``lay`` (dense or
    ``BlockCovariance``): labels (n,) ``"<array>.<param>"`` with param in x, y, z (m), rx, ry, rz (rad,
    rotation about the array's own axes: φ in R Exp(φ)), offset (s), drift; cov (n, n) in those units. Arrays
    in the problem's order, each array's parameters in that order; the reference array's fixed ones, those
    the data leave undetermined (report.json ``undetermined``) and the arrays ``without`` (indices: refitted
    alone, no uncertainty claimed) are absent."""
    labels, idx = [], []
    skip = _undetermined(p)   # undetermined parameters have no covariance (the gauge fixes only some of them)
    for i, name in enumerate(p.names):
        if i in without:
            continue
        for a in ARRAY_PARAMS:
            if (i, a.key) in skip:
                continue
            cols = np.atleast_1d(getattr(lay, a.key)[i])
            for col, label in zip(cols, a.components):
                if col >= 0:
                    labels.append(f"{name}.{label}")
                    idx.append(int(col))
    idx = np.asarray(idx, int)
    return labels, cov_block(cov, idx)
