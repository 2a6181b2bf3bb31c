"""``calibration/calibration.json``: one self-describing file with everything a downstream tool needs.

Written beside arrays.csv, sources.csv and report.json by ``calib estimate`` and ``calib run`` (docs/formats.md,
"calibration.json"): format version, reference array, frame / quaternion / clock conventions and units, and per
array its pose, its microphones in its own frame and in the reference frame (one row per WAV channel), its
clock (every term that maps its local time to the emitter's and the reference array's time), 1-σ, and the full
covariance of the array parameters. :mod:`calib.pipeline.formats.results` reads it back into typed objects.
"""
from __future__ import annotations

import numpy as np

from calib import __version__
from calib.clock import time_bases
from calib.errors import InputError
from calib.robust import mad_std
from calib.tables import ARRAY_PARAMS

FORMAT_NAME = "calib-calibration"
FORMAT_VERSION = 1
CONVENTIONS = {
    "frame": "the reference array's frame is the world frame (its position 0, its rotation I); x, y, z right-handed",
    "rotation": "R (3x3) maps vectors from the array's own frame into the reference frame",
    "quaternion": "scalar-first [qw, qx, qy, qz], unit norm, qw >= 0 (as arrays.csv; scipy's default and ROS "
                  "are scalar-last [qx, qy, qz, qw])",
    "mics": "one [x, y, z] per WAV channel, in WAV channel order, in the array's own frame",
    "mics_reference": "the same microphones in the reference frame: R · m + position",
    "rotation_std": "std of the rotation about the array's own x, y, z axes: φ in R · Exp(φ)",
    "doa": "directions point from the array toward the source, in the array's own frame",
}
UNITS = {"position": "m", "time": "s", "drift": "1 (s per s)", "rotation_std": "rad", "speed_of_sound": "m/s",
         "chirp_drift_bias": "s (per unit drift)"}
CLOCK_MODEL = ("T_i = (1 + drift_i) * (t - t0) + offset_i + reference_offset + h_i(t - t0) [+ chirp_drift_bias * "
               "drift_i]: T_i the array's local time (WAV sample / fs; fs its clock's sample_rate where given, else "
               "its WAV header's), t the emitter's time (events.csv t_emit), t0 the first event's t_emit. h_i: the "
               "array's clock steps (samples inserted: size > 0; dropped: size < 0, applied from their time, the "
               "middle of the interval between the two events they lie between) and drift terms (quadratic: slope * "
               "u^2 / 2; hinge: change * max(0, u - time)); absent: 0. The bracketed term applies to arrival times "
               "measured by matched filtering the calibration chirp (as calib's frontend does), not to other sounds. "
               "An array whose sample_rate differs from its header_sample_rate (r = sample_rate / "
               "header_sample_rate, r_ref the reference array's, 1 where not given): on its header's time base (WAV "
               "sample / header_sample_rate) its local time is r * T_i, its drift r * (1 + drift_i) - 1 and its "
               "offset r * offset_i + (r - r_ref) * reference_offset.")
# the keys of an array's clock model (report.json ``clock.arrays``) copied into its calibration.json ``clock``
CLOCK_MODEL_KEYS = ("drift_model", "steps", "drift_terms", "nominal_rate")
# A clock offset seen through coarse detections: fewer than this many matched events → no estimate.
MIN_ANCHOR_EVENTS = 2


def reference_offset(meta, arrays, sources, events):
    """The reference array's absolute clock offset τ_ref (its local time at emitter time t0) and its 1-σ.

    From ``meta["reference_detections_s"]`` (the frontend's detection times of the reference array), the
    calibrated source positions and the reference's drift: d_j = (1 + δ)(t_j − t0 + |s_j − x_ref|/c) + τ + βδ.
    Returns (tau, std, n) or (None, None, 0) when the features carry no detections. ``std`` is the scatter of
    the median only; the detector's systematic error (tens of µs, docs/formats.md) is not in it.
    """
    dets = meta.get("reference_detections_s") or {}
    if sources is None or len(dets) < MIN_ANCHOR_EVENTS:
        return None, None, 0
    ref = arrays.set_index("array").loc[meta["reference_array"]]
    x_ref, drift = ref[["x", "y", "z"]].to_numpy(float), float(ref["drift"])
    ev = events.set_index("event")["t_emit"]
    src = sources.set_index("event")[["x", "y", "z"]]
    try:
        keep = [int(e) for e in dets if int(e) in src.index and int(e) in ev.index
                and np.isfinite(src.loc[int(e)].to_numpy(float)).all()]   # (a diverged solve's are unknown)
    except (TypeError, ValueError):
        raise InputError("meta.json: 'reference_detections_s' keys must be event ids") from None
    if len(keep) < MIN_ANCHOR_EVENTS:
        return None, None, 0
    try:
        d = np.array([float(dets[str(e)] if str(e) in dets else dets[e]) for e in keep])
    except (TypeError, ValueError):
        raise InputError("meta.json: 'reference_detections_s' must map event ids to times (s)") from None
    t = ev.loc[keep].to_numpy(float) - float(events["t_emit"].min())
    rng = np.linalg.norm(src.loc[keep].to_numpy(float) - x_ref, axis=1) / float(meta["speed_of_sound"])
    beta = float(meta.get("chirp_drift_bias") or 0.0)
    tau = d - (1.0 + drift) * (t + rng) - beta * drift
    center = float(np.median(tau))
    mad_sigma = float(mad_std(tau, center=center))  # robust std of one detection
    return center, mad_sigma / np.sqrt(len(tau)), len(tau)


def mic_geometry(meta):
    """{array: (M, 3) ndarray} from meta.json's optional ``mics`` (empty dict when absent).

    Raises InputError for an unknown array or rows that are not finite [x, y, z]."""
    out = {}
    mics = meta.get("mics") or {}
    if not isinstance(mics, dict):
        raise InputError("meta.json: 'mics' must map array names to [[x, y, z], ...]")
    for name, m in mics.items():
        if name not in meta["arrays"]:
            raise InputError(f"meta.json: 'mics' names unknown array {name!r}")
        try:
            m = np.asarray(m, float)
        except (TypeError, ValueError):
            m = np.zeros(0)
        if m.ndim != 2 or m.shape[1] != 3 or m.shape[0] < 1 or not np.all(np.isfinite(m)):
            raise InputError(f"meta.json: 'mics' of {name!r} must be a non-empty list of finite [x, y, z]")
        out[name] = m
    return out


def _std(row, param):
    """A per-array parameter's 1-σ: a list over its components (a number for one), None where unknown."""
    vals = [row.get(c, np.nan) for c in param.std_columns]
    vals = None if all(v is None or not np.isfinite(v) for v in vals) else [float(v) if np.isfinite(v) else None
                                                                              for v in vals]
    return vals[0] if vals and len(vals) == 1 else vals


def _array_entry(row, mics, tau_ref, undetermined=(), clock_model=None, rates=(None, None)):
    """One array's entry: pose, mics (own and reference frame), clock, 1-σ, and what the data left
    undetermined (report.json ``undetermined`` of this array: parameter names, the axis of a linear array);
    ``clock_model``: its report.json ``clock.arrays`` entry (steps, drift terms, a wrong nominal rate);
    ``rates``: (the rate (Hz) its local time counts WAV samples at, the rate its WAV header states), (None, None):
    its header's (:func:`calib.clock.time_bases`)."""
    from scipy.spatial.transform import Rotation  # (~0.1 s to load: not at every command's start)

    pos = row[["x", "y", "z"]].to_numpy(float)
    quat = row[["qw", "qx", "qy", "qz"]].to_numpy(float)
    R = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    offset, drift = float(row["offset"]), float(row["drift"])
    axis = next((list(u["axis"]) for u in undetermined if u.get("axis") is not None), None)
    return {
        "name": str(row["array"]),
        "position": pos.tolist() if np.isfinite(pos).all() else None,   # null: unknown (a diverged solve)
        "quaternion": quat.tolist(),
        "rotation_matrix": R.tolist(),
        "mics": None if mics is None else mics.tolist(),
        "mics_reference": None if mics is None else (mics @ R.T + pos).tolist(),
        "clock": {"offset": offset, "drift": drift,
                  "offset_emitter": None if tau_ref is None else offset + tau_ref, "sample_rate": rates[0],
                  "header_sample_rate": rates[1],
                  **{k: (clock_model or {}).get(k) for k in CLOCK_MODEL_KEYS if clock_model}},
        "std": {("rotation" if a.rotation else a.label): _std(row, a) for a in ARRAY_PARAMS},
        "undetermined": [u["parameter"] for u in undetermined],
        "axis": axis,   # linear arrays / mic pairs: the axis (own frame) whose direction is calibrated
    }


def array_covariance_of(calib, features):
    """(labels, covariance) of the array parameters: the one ``calibrate`` computed with the std columns, or
    for a calibration read from disk through the estimator's public API; (None, None) when there is none."""
    if calib.get("array_covariance") is not None:
        return calib["array_covariance"]
    from calib.estimator import array_covariance, rebuild

    model = rebuild(features, calib)
    if model is None:
        return None, None
    return array_covariance(model)


def calibration_document(calib, features):
    """The calibration.json dict of a calibration (arrays, sources, report) and the features it came from."""
    meta, arrays, report = features["meta"], calib["arrays"], calib.get("report") or {}
    speed = report.get("speed_of_sound") or {}
    if speed.get("estimated"):   # the speed of sound the estimator solved: every range of this calibration uses it
        meta = {**meta, "speed_of_sound": float(speed["value_m_s"])}
    events = features["events"]
    tau, tau_std, n_anchor = reference_offset(meta, arrays, calib.get("sources"), events)
    mics = mic_geometry(meta)
    order = {n: k for k, n in enumerate(meta["arrays"])}
    rows = sorted((r for _, r in arrays.iterrows()), key=lambda r: order.get(r["array"], len(order)))
    labels, cov = array_covariance_of(calib, features)
    src = calib.get("sources")
    bases = time_bases(meta)
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "software": {"name": "calib", "version": __version__},
        "reference_array": meta["reference_array"],
        "speed_of_sound": float(meta["speed_of_sound"]),
        # how that c was found: declared (session.toml / meta.json) or solved with its 1-σ (m/s); None from a
        # report without it
        "speed_of_sound_fit": {k: speed.get(k) for k in ("declared_m_s", "std_m_s", "estimated")} if speed else None,
        "conventions": CONVENTIONS,
        "units": UNITS,
        "clock": {
            "model": CLOCK_MODEL,
            "t0": float(events["t_emit"].min()),
            "reference_offset": tau,
            "reference_offset_std": tau_std,
            "reference_offset_events": n_anchor,
            "chirp_drift_bias": float(meta.get("chirp_drift_bias") or 0.0),
            "drift_reference": report.get("drift_reference"),
            # emission times off by a term every array saw (steps / drift terms, as an array's): events.csv
            # time = true emission time − h_emitter
            "emitter": {k: v for k, v in ((report.get("clock") or {}).get("emitter") or {}).items()
                        if k in CLOCK_MODEL_KEYS} or None,
        },
        "arrays": [_array_entry(r, mics.get(r["array"]), tau,
                                [u for u in report.get("undetermined") or [] if u.get("array") == r["array"]],
                                ((report.get("clock") or {}).get("arrays") or {}).get(r["array"]),
                                bases.get(r["array"], (None, None)))
                   for r in rows],
        "covariance": None if labels is None else {"parameters": labels, "matrix": np.asarray(cov)},
        # the odometry-frame rotation when the estimator estimated it (report.json always says whether)
        "odometry_frame": (report.get("odometry_frame") if (report.get("odometry_frame") or {}).get("estimated")
                           else None),
        "sources": None if src is None else [
            {"event": int(r["event"]), "position": [float(r["x"]), float(r["y"]), float(r["z"])]
             if np.isfinite(r[["x", "y", "z"]].to_numpy(float)).all() else None}
            for _, r in src.iterrows()],
    }
