"""A WAV header that states the wrong sample rate: measured from the chirps, and the array's samples taken at it.

A board whose file says 48 kHz but samples at 44.1 kHz (or a rate 1 % off) records every interval between
chirps 8 % (1 %) longer than the emission times say. No crystal drifts that far (their drifts are ≤ 1e-4), the
frontend's association only searches |δ| ≤ 1e-3, and its matched filter is built at the stated rate. Left alone,
such an array is lost (issue 28: 7.3 m). The chirps' spacing measures the true rate to ~1e-5 over a session:

1. each array's detection times against the emission times give its clock scale s (all pairs of intervals,
   ``frontend.consistency.clock_scale``: whatever its size), then refined by a straight-line fit of the
   detections matched at that scale;
2. an array whose scale is off by more than ``CLOCK_FAIL`` (from setupcheck: a wrong header, not a drift), with
   no rate declared in session.toml, is extracted again at the measured rate (the nearest standard rate when
   one is within ``STANDARD_FIT``), exactly as a declared ``sample_rate`` would be; the chirps' spacing holds
   the source's range changes too, so a first solve's drift of that array refines the rate, and the arrays are
   extracted once more when it moved by more than ``RATE_REFINE``;
3. features/meta.json ``header_rates`` records it ({array: {header, used, scale, support}}), the set-up check
   names it (a ``suspect`` finding: the user should declare the rate or fix the header) and the calibration's
   clock times are local times at the rate used.

When every array is off by one scale, the emission times are wrong (events.csv), not the headers: nothing is
changed (the set-up check names events.csv).
"""
from __future__ import annotations

import numpy as np

# A standard rate within this of the measured one is the board's nominal rate (a crystal's drift, ≤ 1e-4,
# plus the measurement's error); otherwise the measured rate itself is used (the drift absorbs the rest).
STANDARD_FIT = 5e-4
# A detection matches the event predicted at the coarse scale within this (s): chirps are ≥ 0.5 s apart.
MATCH_TOL = 0.1
MIN_MATCHED = 3   # detections for the straight-line fit
# A first solve's drift beyond this re-extracts at the refined rate: half the frontend's Doppler-bank step
# (1.4e-4 for a 0.5 s, 0.5-4 kHz sweep, pipeline/retime.py), where a template's stretch starts to bias timing.
RATE_REFINE = 7e-5


def refine_scale(times, t_emit, scale, tol=MATCH_TOL):
    """(scale, n matched): the straight-line fit ``time = scale · t_emit + b`` of the detections ``times`` (s,
    local clock) matched to the emission times ``t_emit`` predicted at the coarse ``scale`` (offset: the
    median residual of each detection against its nearest predicted event)."""
    times, t_emit = np.sort(np.asarray(times, float)), np.sort(np.asarray(t_emit, float))
    for _ in range(2):
        pred = scale * t_emit
        # the offset: the mode of every (detection − predicted emission) pair, to a tolerance
        lags = (times[:, None] - pred[None, :]).ravel()
        bins = np.round(lags / tol).astype(np.int64)
        vals, counts = np.unique(bins, return_counts=True)
        b = float(np.median(lags[bins == vals[np.argmax(counts)]]))
        k = np.abs(times[:, None] - (pred[None, :] + b))
        near = np.argmin(k, axis=1)
        ok = k[np.arange(len(times)), near] < tol
        if ok.sum() < MIN_MATCHED:
            return scale, int(ok.sum())
        scale = float(np.polyfit(t_emit[near[ok]], times[ok], 1)[0])
    return scale, int(ok.sum())


def rate_corrections(session, diagnostics):
    """{array: {"header": Hz, "used": Hz, "scale", "support", "matched"}} for the arrays whose stated rate the
    chirps contradict (module doc); {} when none or when every array is off alike (events.csv's times)."""
    from calib.frontend.consistency import clock_scale
    from calib.pipeline.setupcheck import CLOCK_FAIL, CLOCK_SUPPORT

    t_emit = session["events"]["t_emit"].to_numpy(float)
    arrays = (diagnostics or {}).get("arrays", {})
    found = {}
    for a in session["arrays"]:
        d = arrays.get(a["name"]) or {}
        times = np.array([x["time"] for x in d.get("detections", [])], float)
        if a.get("sample_rate") is not None or not d.get("fs"):
            continue   # a declared rate is the user's word
        s, support = clock_scale(times, t_emit)
        if not (support >= CLOCK_SUPPORT and abs(s - 1) > CLOCK_FAIL):
            continue
        s, matched = refine_scale(times, t_emit, s)
        found[a["name"]] = {"header": int(d["fs"]), "scale": s, "support": float(support), "matched": matched}
    if len(found) == len(session["arrays"]) > 1 and np.ptp([f["scale"] for f in found.values()]) < CLOCK_FAIL:
        return {}   # the emission times, not the headers (setupcheck.clock_findings names events.csv)
    for f in found.values():
        f["used"] = nominal_rate(f["header"] * f["scale"])
    return found


def nominal_rate(rate):
    """The rate (Hz) to take a board's samples at, from a measured one: the nearest standard rate when one is
    within ``STANDARD_FIT``, else the measured rate to the hertz."""
    from calib.pipeline.setupcheck import STANDARD_RATES

    near = min(STANDARD_RATES, key=lambda r: abs(r / rate - 1))
    return int(near) if abs(near / rate - 1) < STANDARD_FIT else int(round(rate))


def refine_rates(session, feats, corrections):
    """The corrections with each array's rate refined by the drift a first solve of ``feats`` (extracted at
    the corrected rates) gives it: the chirps' spacing includes the source's range changes (metres over a
    session: up to ~1e-3 of the rate), the solve's drift does not. Returns (corrections, changed: an array's
    rate moved by more than ``RATE_REFINE``). A solve that fails or does not converge changes nothing."""
    from calib.estimator import ObservabilityError, calibrate

    from calib.pipeline.features import add_session_meta

    try:   # (as the moving source's first solve, pipeline/retime.py: stated sigmas, linear clock)
        sol = calibrate(add_session_meta(feats, session, {}), outputs="solution", clock_model="linear",
                        noise="meta")
    except (ObservabilityError, ValueError):
        return corrections, False
    if not sol["converged"]:
        return corrections, False
    drift = dict(zip((str(n) for n in sol["problem"].names), np.asarray(sol["state"].drift, float)))
    out, changed = {}, False
    for name, f in corrections.items():
        d = drift.get(name, 0.0) if name not in sol["unreliable_arrays"] else 0.0
        rate = nominal_rate(f["used"] * (1.0 + d))
        changed |= abs(rate / f["used"] - 1) > RATE_REFINE
        out[name] = {**f, "used": rate if abs(rate / f["used"] - 1) > RATE_REFINE else f["used"],
                     "refined_by_drift": float(d)}
    return out, changed


def with_rates(session, corrections):
    """The session with each corrected array's ``sample_rate`` set to the rate used (a copy)."""
    arrays = [{**a, "sample_rate": corrections[a["name"]]["used"]} if a["name"] in corrections else a
              for a in session["arrays"]]
    return {**session, "arrays": arrays}
