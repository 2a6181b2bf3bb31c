"""The numeric problem: features dict → index arrays, and the state ↔ parameter-vector layout.

A *problem* is a dict of numpy arrays (built once per data set)::

    names (N,) array names, ref (int) index of the reference array, c (m/s), beta (s per unit drift),
    t (K,) emission times minus t_0 (s), events (K,) event ids, odom (K, 3) cumulative odometry (m),
    tm_ev, tm_arr, tm_val (n_m,)         TDOA-M rows: event index, array index, value (s)
    ts_arr, ts_a, ts_b, ts_val (n_s,)    TDOA-S rows: array index, from/to event index, value (s)
    doa_ev, doa_arr (n_d,), doa_u (n_d, 3)   DOA rows: event index, array index, unit vector (array frame)
    sigma_tdoa (s), sigma_doa (rad, per tangent axis), sigma_odo (m), sigma_emit (s or 0 = off);
    sigma_tdoa_s, sigma_tdoa_m: the TDOA sigma per type (both sigma_tdoa unless re-estimated)
    fold (N, 3) mic-plane normal of arrays whose DOAs are mirror-ambiguous (zeros elsewhere)
    *_row (n,) the line of each measurement in its CSV file, header = line 1 (for outlier reports)

A *state* is a dict: ``x`` (N, 3), ``R`` (N, 3, 3), ``offset`` (N,), ``drift`` (N,), ``s`` (K, 3),
``e`` (K,) emission-time corrections (s; e[0] = 0), ``odo_yaw`` (1,) the odometry frame's rotation about
the vertical (rad; see ``factors.odometry_frame``).

``odo_yaw_free`` (bool, problem) says whether that yaw is estimated (``build_problem(odometry_yaw=...)``).

A *layout* says which of them are free in a solve and where they sit in the parameter vector.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# Documented defaults when meta.json gives no sigmas (the paper's real-data settings).
DEFAULT_SIGMA_TDOA = 1e-4      # s
DEFAULT_SIGMA_DOA_DEG = 5.0    # deg per tangent axis
DEFAULT_SIGMA_ODO = 0.01       # m per axis per step

# The readers (calib.pipeline.formats.io) add each row's line in its CSV file (header = 1) under this column, so
# outliers can be reported by file line; it lives in memory only and is never written.
LINE_COLUMN = "csv_line"


def sigma_doa_per_axis(sigma_deg):
    """meta ``sigma_doa_deg`` → std per tangent axis of the DOA direction error (rad).

    ``sigma_doa_deg`` is the standard deviation of the DOA error along each of the two axes
    perpendicular to the true direction (the weighting of the paper's code, where each component of the
    unit-vector residual has std 2·sin(σ/2) ≈ σ). The paper's simulation draws a rotation about an isotropic
    random axis by N(0, σ²); that is σ/√3 per axis (``pipeline.simulate.featsim`` writes it so).
    """
    return float(np.deg2rad(sigma_deg))


def build_problem(features, *, use_tdoa_s=True, use_tdoa_m=True, use_doa=True, sigma_emit=0.0, odometry_yaw=False):
    """Index the measurements of a (validated) features dict. See module docstring for the keys."""
    meta = features["meta"]
    names = np.asarray(meta["arrays"], dtype=object)
    idx = {n: k for k, n in enumerate(names)}
    ev = features["events"]
    events = ev["event"].to_numpy(int)
    eidx = {e: k for k, e in enumerate(events)}
    t_emit = ev["t_emit"].to_numpy(float)
    odom = ev[["odom_x", "odom_y", "odom_z"]].to_numpy(float)

    def rows(df, use):
        return df if use else df.iloc[:0]

    tm = rows(features["tdoa_m"], use_tdoa_m)
    ts = rows(features["tdoa_s"], use_tdoa_s)
    doa = rows(features["doa"], use_doa)
    p = {
        "names": names,
        "ref": idx[meta["reference_array"]],
        "c": float(meta["speed_of_sound"]),
        "beta": float(meta.get("chirp_drift_bias", 0.0) or 0.0),
        "t": t_emit - t_emit[0],
        "events": events,
        "odom": odom,
        "tm_ev": np.array([eidx[e] for e in tm["event"]], dtype=int),
        "tm_arr": np.array([idx[a] for a in tm["array"]], dtype=int),
        "tm_val": tm["tdoa"].to_numpy(float),
        "tm_row": _lines(tm),
        "ts_arr": np.array([idx[a] for a in ts["array"]], dtype=int),
        "ts_a": np.array([eidx[e] for e in ts["from_event"]], dtype=int),
        "ts_b": np.array([eidx[e] for e in ts["to_event"]], dtype=int),
        "ts_val": ts["tdoa"].to_numpy(float),
        "ts_row": _lines(ts),
        "doa_ev": np.array([eidx[e] for e in doa["event"]], dtype=int),
        "doa_arr": np.array([idx[a] for a in doa["array"]], dtype=int),
        "doa_u": doa[["ux", "uy", "uz"]].to_numpy(float).reshape(-1, 3),
        "doa_row": _lines(doa),
        "sigma_tdoa": float(meta.get("sigma_tdoa", DEFAULT_SIGMA_TDOA)),
        "sigma_tdoa_s": float(meta.get("sigma_tdoa", DEFAULT_SIGMA_TDOA)),
        "sigma_tdoa_m": float(meta.get("sigma_tdoa", DEFAULT_SIGMA_TDOA)),
        "sigma_doa": float(sigma_doa_per_axis(meta.get("sigma_doa_deg", DEFAULT_SIGMA_DOA_DEG))),
        "sigma_odo": float(meta.get("sigma_odo", DEFAULT_SIGMA_ODO)),
        "sigma_emit": float(sigma_emit),
    }
    # Planar arrays without a stated hemisphere (meta doa_mirror_normals): their DOAs are known up to the
    # mirror image across the mic plane (normal n, array frame).
    p["fold"] = np.zeros((len(names), 3))
    for name, n in (meta.get("doa_mirror_normals") or {}).items():
        p["fold"][idx[name]] = np.asarray(n, float) / np.linalg.norm(n)
    # fold the measured DOAs of those arrays to n·u >= 0 whatever side a frontend reported
    nf = p["fold"][p["doa_arr"]]
    dots = np.einsum("ka,ka->k", nf, p["doa_u"])
    p["doa_u"] = np.where((dots < 0)[:, None], p["doa_u"] - 2.0 * dots[:, None] * nf, p["doa_u"])
    p["N"], p["K"] = len(names), len(events)
    _split_cones(p, meta, idx)
    # orientation estimated only for arrays with DOAs for >= MIN_DOA_EVENTS events (single microphones and
    # arrays without usable DOAs: position and clock from the TDOAs, orientation reported undetermined)
    n_doa = np.bincount(p["doa_arr"], minlength=len(names)) if len(p["doa_arr"]) else np.zeros(len(names), int)
    n_cone = np.bincount(p["cone_arr"], minlength=len(names)) if len(p["cone_arr"]) else np.zeros(len(names), int)
    p["rot_free"] = (n_doa >= MIN_DOA_EVENTS) | (n_cone >= MIN_DOA_EVENTS)
    p["n_doa_events"] = n_doa
    # a lone DOA of an array whose orientation is not estimated says nothing: leave it out
    useless = ~p["rot_free"][p["doa_arr"]] & (p["doa_arr"] != p["ref"])
    if useless.any():
        for key in ("doa_ev", "doa_arr", "doa_u", "doa_row"):
            p[key] = p[key][~useless]
    p["odo_yaw_free"] = bool(odometry_yaw) and odometry_yaw_observable(p)
    return p


MIN_DOA_EVENTS = 2   # DOAs (events) an array needs for its orientation


def _split_cones(p, meta, idx):
    """Move the DOA rows of arrays listed in meta ``doa_axes`` (linear arrays, 2-mic pairs) to cone rows.

    ``doa_axes``: {array: axis}, the axis a unit vector in the array frame (sign free; usually a
    coordinate axis). Such an array measures only the angle θ between its axis and the source direction;
    its doa.csv rows hold any unit vector on that cone (the estimator uses cos θ = axis · u). Adds
    ``cone_ev``, ``cone_arr``, ``cone_cos``, ``cone_row`` (n_c,), ``cone_axis`` (N, 3), ``rot_fixed_axis``
    (N,) and ``sigma_cone`` (rad). ``rot_fixed_axis`` is the array-frame coordinate axis k nearest the
    array's axis (-1 for other arrays): the rotation component about e_k is not estimated. The roll about
    the axis is not observable; the two components about the other coordinate axes move the axis in every
    direction (φ × a spans the plane ⟂ a when a_k ≠ 0), so they estimate it and fix that gauge.
    """
    N = len(p["names"])
    p["cone_axis"] = np.zeros((N, 3))
    p["rot_fixed_axis"] = -np.ones(N, int)
    for name, ax in (meta.get("doa_axes") or {}).items():
        a = np.asarray(ax, float) / np.linalg.norm(ax)
        k = int(np.argmax(np.abs(a)))
        p["cone_axis"][idx[name]] = a
        p["rot_fixed_axis"][idx[name]] = k
    is_cone = p["rot_fixed_axis"][p["doa_arr"]] >= 0
    p["cone_ev"], p["cone_arr"], p["cone_row"] = p["doa_ev"][is_cone], p["doa_arr"][is_cone], p["doa_row"][is_cone]
    p["cone_cos"] = np.clip(np.einsum("ka,ka->k", p["cone_axis"][p["cone_arr"]], p["doa_u"][is_cone]), -1.0, 1.0)
    for key in ("doa_ev", "doa_arr", "doa_u", "doa_row"):
        p[key] = p[key][~is_cone]
    p["sigma_cone"] = p["sigma_doa"]


# The yaw of the odometry frame needs horizontal motion: a spread of the odometry across the vertical
# below this (m, RMS) leaves it to the noise.
MIN_HORIZONTAL_SPREAD = 0.05


def odometry_yaw_observable(p):
    """True when the odometry moves horizontally enough (and there are DOAs) to fix its yaw."""
    o = p["odom"][:, :2] - p["odom"][:, :2].mean(0)
    return bool(len(p["doa_u"]) > 0 and p["K"] >= 3 and np.sqrt(np.mean(np.sum(o * o, axis=1))) > MIN_HORIZONTAL_SPREAD)


def _lines(df):
    """Line numbers of the rows in their CSV file (header = line 1), or data-row positions + 2 in memory."""
    return df[LINE_COLUMN].to_numpy(int) if LINE_COLUMN in df else df.index.to_numpy(int) + 2


def empty_state(p):
    """A state with every array at the origin, identity rotations, zero clocks and sources."""
    N, K = p["N"], p["K"]
    return {"x": np.zeros((N, 3)), "R": np.tile(np.eye(3), (N, 1, 1)), "offset": np.zeros(N),
            "drift": np.zeros(N), "s": np.zeros((K, 3)), "e": np.zeros(K), "odo_yaw": np.zeros(1)}


def copy_state(st):
    return {k: v.copy() for k, v in st.items()}


def make_layout(p, *, rotations=True, ref_drift=None, emission=None, sources=True, arrays=None, odo_yaw=None):
    """Positions of the free parameters in the vector.

    Returns a dict of index arrays (-1 where a parameter is fixed):
    ``x`` (N, 3), ``rot`` (N, 3), ``offset`` (N,), ``drift`` (N,), ``s`` (K, 3), ``e`` (K,), and ``n``.
    The reference array's position, rotation and offset are always fixed (they define the frame and the
    time origin). Its drift is free when TDOA-S is present (``ref_drift=None`` decides that).
    ``arrays`` restricts the free array parameters to these indices (others are fixed).
    ``odo_yaw`` (1,): the odometry frame's yaw, free when the problem says so (``odo_yaw_free``) and the
    sources are free (``odo_yaw=None``), or as forced.
    """
    N, K, ref = p["N"], p["K"], p["ref"]
    if ref_drift is None:
        ref_drift = len(p["ts_val"]) > 0
    if emission is None:
        emission = p["sigma_emit"] > 0
    free_arr = np.zeros(N, bool)
    free_arr[np.arange(N) if arrays is None else np.asarray(arrays, int)] = True
    lay = {"x": -np.ones((N, 3), int), "rot": -np.ones((N, 3), int), "offset": -np.ones(N, int),
           "drift": -np.ones(N, int), "s": -np.ones((K, 3), int), "e": -np.ones(K, int)}
    n = 0

    def take(k):
        nonlocal n
        out = np.arange(n, n + k)
        n += k
        return out

    for i in range(N):
        if not free_arr[i]:
            continue
        if i != ref:
            lay["x"][i] = take(3)
            if rotations and p.get("rot_free", np.ones(N, bool))[i]:
                k_fix = p.get("rot_fixed_axis", -np.ones(N, int))[i]
                if k_fix >= 0:   # roll about a linear array's axis: not observable, not estimated
                    lay["rot"][i, [c for c in range(3) if c != k_fix]] = take(2)
                else:
                    lay["rot"][i] = take(3)
            lay["offset"][i] = take(1)[0]
        if i != ref or ref_drift:
            lay["drift"][i] = take(1)[0]
    if sources:
        lay["s"][:] = take(3 * K).reshape(K, 3)
    if emission and K > 1:
        lay["e"][1:] = take(K - 1)
    if odo_yaw is None:
        odo_yaw = bool(p.get("odo_yaw_free", False)) and sources
    lay["odo_yaw"] = take(1) if odo_yaw else -np.ones(1, int)
    lay["n"] = n
    return _without_fixed(lay, p.get("fixed_cols"))


def _without_fixed(lay, fixed):
    """Drop the columns the data leave undetermined (``p["fixed_cols"]``: {key: bool mask shaped like
    lay[key]}, set by :func:`calib.estimator.observability.check_observability`) and renumber the rest in order."""
    if not fixed:
        return lay
    for key, mask in fixed.items():
        lay[key] = np.where(mask, -1, lay[key])
    keys = [k for k in lay if k != "n"]
    used = np.zeros(lay["n"], bool)
    for k in keys:
        used[lay[k][lay[k] >= 0]] = True
    new = np.cumsum(used) - 1
    for k in keys:
        lay[k] = np.where(lay[k] >= 0, new[np.maximum(lay[k], 0)], -1)
    lay["n"] = int(used.sum())
    return lay


def retract(st, lay, delta):
    """Apply a parameter step ``delta`` (n,) to a state; rotations by right perturbation R Exp(φ)."""
    out = copy_state(st)
    for key in ("x", "s"):
        m = lay[key] >= 0
        out[key][m] += delta[lay[key][m]]
    for key in ("offset", "drift", "e", "odo_yaw"):
        if key not in lay:
            continue
        if key not in out:
            out[key] = np.zeros(len(lay[key]))
        m = lay[key] >= 0
        out[key][m] += delta[lay[key][m]]
    rows = np.flatnonzero(np.any(lay["rot"] >= 0, axis=1))
    if rows.size:
        idx = lay["rot"][rows]
        phi = np.where(idx >= 0, delta[np.maximum(idx, 0)], 0.0)
        out["R"][rows] = st["R"][rows] @ Rotation.from_rotvec(phi).as_matrix()
    return out


def state_to_frames(p, st):
    """State → (arrays DataFrame columns as dict of arrays, sources (K, 3))."""
    q = Rotation.from_matrix(st["R"]).as_quat(scalar_first=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)  # canonical sign: qw >= 0
    return q
