"""``extract_features``: a recording session (docs/formats.md section 1) → features (section 2) + diagnostics.

Per array (each at its own sample rate, all times in seconds on its own clock):
1. matched-filter envelope of the whole recording (read block-wise), peaks → detections (:mod:`frontend.detect`);
2. detections ↔ events by the emission-time pattern (:mod:`frontend.associate`);
3. per matched event, sub-sample chirp start at every mic (:mod:`frontend.timing`);
4. SRP-PHAT DOA on the time-gated direct path (:mod:`frontend.doa`);
5. mic times referred to the array origin with the DOA (a plane wave from ``u`` reaches mic ``m``
   ``u·m/c`` before the origin) and fused robustly → arrival ``a_ij`` of event ``j`` at array ``i``.
TDOA-S and TDOA-M are differences of these arrival times.
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np
import pandas as pd

from calib.blas import single_thread_blas
from calib.geometry import doa_covariance
from calib.errors import InputError
from calib.records import Features
from calib.tables import event_velocities

from . import associate as assoc_mod
from .arrayresult import ArrayResult
from .detect import background, matched_envelope, pick_peaks, redetect, refine_peak
from .diagnostics import envelope_summary
from .doa import band_scatter, cone_vectors, mic_geometry, srp_cone, srp_doa, srp_setup
from .nlos import TRACK_SCALE_MAX, late_arrivals_many, no_direct_path, retime_earlier
from .noise import arrival_sd as claimed_sd, near_field_fit
from .signals import ArrayAudio, chirp_band, chirp_template, read_header
from .timing import (doa_time, drift_bias, estimate_phase, fuse_times, locate, matched_stretch, segment_spectra, shared_setup,
                     spectra_setup, stretch_bank, sweep_time)

DEFAULTS = {
    "threshold": 8.0,        # detection: peak / local background of the matched-filter envelope
    "max_drift": 1e-3,       # association: bound on |clock drift|
    "tolerance": None,       # association: max |arrival − predicted| (s); None = min(0.1, spacing / 4)
    "redetect_threshold": 5.0,  # missed events: re-detected near their predicted time above this score
    "max_distance": 30.0,    # m: the direct path may precede the detected (strongest) peak by this / c
    "search_after": 0.003,   # ... or follow the detection by this much (s)
    "onset_snr": 6.0,        # direct path = earliest peak ≥ this × the noise floor (median before the peak)
    "onset_min_ratio": 0.05,  # ... and ≥ this × the strongest peak (−26 dB), and not a sidelobe of a later one
    "track_tol": 0.010,      # s: an arrival this far off its neighbours' clock-track residuals is doubtful
    "whiten_hz": 500.0,      # GCC whitening: magnitude smoothed over this band (Hz); 0 = plain matched filter
    "grid_deg": 3.0,         # SRP grid spacing (deg), refined locally to 0.02°
    "gate_pulses": 3.0,      # DOA gate: flat over the aperture ± this many pulse widths (1 / bandwidth)
    "min_mic_quality": 0.1,  # a mic whose normalised GCC peak is below this (× the event's best) is ignored
}


def _check_audio(session):
    """Open every WAV's header first, so bad input fails before any work."""
    for a in session["arrays"]:
        read_header(a)


def extract_features(session: Any, progress: Callable[[int, int, str], Any] | None = None, jobs: int = 1,
                     **options: Any) -> tuple[Features, dict[str, Any]]:
    """Features of a recording session.

    Parameters
    ----------
    session : the in-memory session (``calib.pipeline.formats.session.read_session`` of a folder with
        session.toml, the WAVs and events.csv): speed_of_sound, reference_array, events, arrays.
    progress : optional callable ``progress(done, total, message)``, called as arrays are processed.
    jobs : arrays processed at a time, in threads (−1: one per core). The results do not depend on it
        (each array's work is independent and deterministic); the FFTs and most of the numpy work release
        the GIL, so 2 threads cut the wall time by about a quarter to a third (CHANGELOG.md).
    options : overrides of :data:`DEFAULTS`.

    Returns
    -------
    features : :class:`calib.records.Features`, as ``pipeline.formats.io.read_features`` returns them, with
        a ``quality`` column in tdoa_m, tdoa_s and doa (docs/frontend.md).
    diagnostics : dict (JSON-able except keys starting with ``_``): per-array detections, matches,
        missed events, spurious detections, association fit, warnings, timings.
    """
    opt = {**DEFAULTS, **options}
    unknown = set(options) - set(DEFAULTS)
    if unknown:
        raise TypeError(f"unknown option(s): {', '.join(sorted(unknown))}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs == 0 or jobs < -1:
        raise ValueError(f"jobs must be a positive integer or -1 (one per core), got {jobs!r}")
    # single-threaded BLAS: the frontend's products are small (mics × grid, events × taps), and OpenBLAS
    # threads spin on them: ~40 % more CPU for no wall-clock gain (CHANGELOG.md, issue 12)
    with single_thread_blas():
        return _extract(session, progress, opt, jobs)


def _extract(session, progress, opt, jobs=1):
    """:func:`extract_features` with validated options ``opt``."""
    t_start = time.perf_counter()
    _check_audio(session)
    c = session["speed_of_sound"]
    t_emit = session["events"]["t_emit"].to_numpy(float)
    ref = session["reference_array"]
    arrays = session["arrays"]
    order = sorted(range(len(arrays)), key=lambda k: arrays[k]["name"] != ref)  # reference first: β at its rate
    # a source moving during the sweep: what a re-timing with predicted stretches needs (retime_arrivals)
    keep = {} if _max_speed(session["events"]) > 0 else None
    results, beta = _process_arrays(session, order, t_emit, c, opt, progress, jobs, keep)
    if keep is not None:   # before the session-wide checks fill flags and warnings in place
        keep = {"arrays": keep, "raw": {n: _copy_result(r) for n, r in results.items()}, "beta": beta, "opt": opt}
    feats, diag = _finish(session, results, beta, opt, t_start)
    if progress is not None:
        progress(len(arrays), len(arrays), "done")
    if keep is not None:
        diag["_retime"] = keep
        diag["_sweep_times"] = (feats["meta"]["doa_time_s"], feats["meta"]["stretch_time_s"])
    return feats, diag


def _copy_result(r):
    """An :class:`ArrayResult` whose flags and warnings (filled in place by the session-wide checks) are its own."""
    return r.replace(flags=[list(f) for f in r.flags], warnings=list(r.warnings))


def retime_arrivals(session, diag, stretches, min_rows=1):
    """The features again, each (array, event) timed against the template stretched by a GIVEN ε instead of
    the one its own arrival matched best (a source moving during the sweep; ``pipeline/retime.py`` predicts
    ε from a first solve's geometry and the robot's velocity: a direct path heard below a reflection takes the
    reflection's Doppler in the search).

    diag : the diagnostics of :func:`extract_features` on ``session`` (its private ``_retime`` state; absent
    for a source at rest: nothing to do). stretches : {array: (K,) ε per session event (events.csv order),
    NaN = keep the searched one}. Only the events whose given ε falls at least ``min_rows`` bank rows from the
    searched one are timed again (their segments read again, no detection); the others, and arrays not in
    ``stretches``, keep their first-pass timing. Returns (features, diagnostics) as :func:`extract_features`,
    with diagnostics ``retime``: {array: events re-timed}; (None, diag) when there is no state.
    """
    keep = diag.get("_retime")
    if keep is None:
        return None, diag
    t_start = time.perf_counter()
    c, opt = session["speed_of_sound"], keep["opt"]
    t_emit = session["events"]["t_emit"].to_numpy(float)
    results, done = {}, {}
    with single_thread_blas():
        for name, raw in keep["raw"].items():
            eps = stretches.get(name)
            k = keep["arrays"][name]
            change, rows = _changed_rows(k, eps, min_rows)
            done[name] = int(np.sum(change))
            if not done[name]:
                results[name] = _copy_result(raw)
                continue
            st = {**k["st"], "timings": dict(k["st"]["timings"])}
            loc, doa = _relocate(st, k, change, rows, c, opt)
            results[name] = _array_result(st, k["ctx"], loc, t_emit, c, opt, doa)
    feats, out = _finish(session, results, keep["beta"], opt, t_start, diag.get("_sweep_times"),
                         MOTION_MODEL_ERROR_RETIMED)
    out["retime"] = done
    return feats, out


def _changed_rows(k, eps, min_rows):
    """((J,) bool: the events to time again, (J,) int: the bank row of each event's given ε) of one array's
    kept state ``k`` (:func:`time_array`) and ε per session event (None: none given)."""
    ev_idx, bank = k["ctx"]["ev_idx"], k["ctx"]["bank"]
    j = len(ev_idx)
    if eps is None or bank is None:
        return np.zeros(j, bool), np.zeros(j, int)
    grid = bank[1]
    e = np.asarray(eps, float)[ev_idx]
    rows = np.argmin(np.abs(np.nan_to_num(e)[:, None] - grid[None, :]), axis=1)
    # the searched row of each event: its stretch on the grid
    old = np.argmin(np.abs(np.asarray(k["loc"]["stretch"], float)[:, None] - grid[None, :]), axis=1)
    inside = np.isfinite(e) & (np.abs(e) <= grid[-1] + 0.5 * (grid[1] - grid[0]))
    return inside & (np.abs(rows - old) >= min_rows), rows


def _relocate(st, k, change, rows, c, opt):
    """(loc, doa) of an array's kept state ``k`` (:func:`time_array`) with the events ``change`` located
    (:func:`locate_events`) against bank rows ``rows`` and their DOAs (:func:`_direct_path_doa`) again."""
    ctx, loc = k["ctx"], k["loc"]
    x = ArrayAudio(st["a"])
    try:
        t0 = time.perf_counter()
        idx = np.flatnonzero(change)
        new = locate_events(x, ctx["starts"][idx], ctx["setup"], ctx["locate_kw"], workers=1, bank=ctx["bank"],
                            rows=rows[idx])
    finally:
        x.close()
    st["timings"]["retime"] = time.perf_counter() - t0
    doa = _direct_path_doa(new, ctx["mics"], st["fs"], ctx["setup"], ctx["g"], c, opt, st["a"].get("doa_hemisphere"))
    j = len(ctx["ev_idx"])
    return _merge_events(loc, new, idx, j), _merge_events(k["doa"], doa, idx, j, DOA_EVENT_KEYS)


DOA_EVENT_KEYS = ("u", "power", "gap", "band_sd")   # the per-event entries of _direct_path_doa's dict


def _merge_events(old, new, idx, j, keys=None):
    """``old`` (a dict of per-event arrays over J events, and others) with the events ``idx`` from ``new``
    (``keys``: the per-event entries; None: every array of J rows)."""
    out = dict(old)
    for key, v in old.items():
        if (key in keys) if keys is not None else (isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == j):
            w = np.array(v, copy=True)
            w[idx] = new[key]
            out[key] = w
    return out


def _finish(session, results, beta, opt, t_start, sweep_times=None, motion_error=None):
    """The session-wide part of the frontend on the arrays' results: arrivals in the β ε convention, NLOS,
    DOA-spread and motion checks, the feature tables and the diagnostics (``sweep_times``: meta
    (doa_time_s, stretch_time_s) when already known; ``motion_error``: :func:`motion_sd`'s fraction, None:
    MOTION_MODEL_ERROR).
    Returns (Features, diagnostics)."""
    c = session["speed_of_sound"]
    events = session["events"]
    ev_ids = events["event"].to_numpy(int)
    # timed against the template stretched by ε̂ (Doppler bank): the arrival is the sweep start's plus
    # β (ε − ε̂), linear in the small mismatch; adding β ε̂ gives the β ε convention of a static template
    results = {n: r.replace(arrival=r.arrival + beta * r.stretch) for n, r in results.items()}
    results = flag_nlos(results, events, lambda eps: beta * eps, c)
    flag_doa_spread(results)
    flag_no_direct(results)
    warn_moving(results, events)

    feats = _tables(session, results, ev_ids, beta)
    if _max_speed(events) > 0:
        meta = feats["meta"]
        ref = session["reference_array"]
        a_ref = next(a for a in session["arrays"] if a["name"] == ref)
        # when in the sweep the DOA looks at the source, and whose range rate the timing follows
        meta["doa_time_s"], meta["stretch_time_s"] = sweep_times or _reference_sweep_times(a_ref, session, c, opt,
                                                                                             beta)
        if "sigma_tdoa" in meta.get("sigmas_estimated", []):
            motion = motion_sd(events, c, beta, motion_error or MOTION_MODEL_ERROR)
            meta["sigma_tdoa"] = float(np.hypot(meta["sigma_tdoa"], motion))
    diag = _diagnostics(session, results, ev_ids, beta, time.perf_counter() - t_start)
    return Features.from_dict(feats), diag


def _process_arrays(session, order, t_emit, c, opt, progress, jobs, keep=None):
    """({array name: :func:`process_array` result} in ``order``, β of the reference ``order[0]``
    (:func:`_reference_beta`)); ``jobs`` arrays at a time in threads (each array's FFTs then
    single-threaded), β as one more task. keep : dict filled with each array's timing state
    (:func:`time_array`), or None.

    Progress and errors follow ``order`` whatever finishes first, so a bad file is reported the same way
    with any ``jobs``; an error or interrupt cancels the arrays not started (the running ones finish).
    """
    arrays = session["arrays"]
    jobs = min(len(order), (os.cpu_count() or 1) if jobs == -1 else jobs)
    if jobs <= 1:
        results = {}
        for n_done, k in enumerate(order):
            _progress(progress, n_done, arrays, k)
            results[arrays[k]["name"]] = process_array(arrays[k], session, t_emit, c, opt, keep=keep)
        return results, _reference_beta(arrays[order[0]], session, c, opt)
    with ThreadPoolExecutor(jobs, thread_name_prefix="calib-array") as pool:
        futures = [pool.submit(process_array, arrays[k], session, t_emit, c, opt, 1, keep) for k in order]
        futures.append(pool.submit(_reference_beta, arrays[order[0]], session, c, opt))
        try:
            results = {}
            for n_done, k in enumerate(order):
                _progress(progress, n_done, arrays, k)
                results[arrays[k]["name"]] = futures[n_done].result()
            return results, futures[-1].result()
        except BaseException:
            for f in futures:
                f.cancel()
            raise


def _progress(progress, n_done, arrays, k):
    if progress is not None:
        progress(n_done, len(arrays), f"array {arrays[k]['name']}")


def process_array(a, session, t_emit, c, opt, fft_workers=-1, keep=None):
    """Detection, association, timing and DOA for one array (``fft_workers``: threads of the segments'
    FFTs, :func:`timing.segment_spectra`; ``keep``: :func:`time_array`)."""
    return time_array(detect_array(a, session, t_emit, c, opt), session, t_emit, c, opt, fft_workers, keep)


def detect_array(a, session, t_emit, c, opt):
    """:func:`process_array`'s first phase: the recording opened, its chirps detected and associated with
    the events. Returns the state :func:`time_array` continues from (the recording still open)."""
    timings = {}
    t0 = time.perf_counter()
    x = ArrayAudio(a)  # read on demand (blocks, event segments): memory bounded whatever the length
    fs = x.fs
    timings["read"] = time.perf_counter() - t0
    try:
        template = chirp_template(session["chirp"], fs)
        band = chirp_band(session["chirp"], template, fs)
        dur = len(template) / fs
        t0 = time.perf_counter()
        # detection on the sum of the channels: one FFT instead of M; a few-cm array sums the chirp's band
        # nearly coherently (on simulated rooms the weakest chirp stood out as well as with 3 channels' envelopes)
        env, dec = matched_envelope(x.channel_sum(), template, fs, band)  # (1, N): summed as read
        env_rate = fs / dec
        spacing = np.min(np.diff(t_emit)) if len(t_emit) > 1 else np.inf
        levels = background(env, env_rate)   # shared by the detection and the second look at missed events
        idx, score = pick_peaks(env, env_rate, min(dur, 0.5 * spacing), opt["threshold"], levels=levels)
        det_t = refine_peak(env, idx) / env_rate if len(idx) else np.zeros(0)
        timings["detect"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        asc = assoc_mod.associate(det_t, score, t_emit, tol=opt["tolerance"], max_drift=opt["max_drift"])
        if asc["n_matched"] < 2:
            raise InputError(f"{a['wav']}: found {asc['n_matched']} chirp(s) matching the events in events.csv "
                             f"({len(det_t)} detection(s)); need at least 2")
        det_t, score, redetected = _redetect_missed(env, env_rate, det_t, score, asc, t_emit, c, opt, levels)
        timings["associate"] = time.perf_counter() - t0
        x.release()  # the detection's last pages: the timing reads only the event segments
    except BaseException:
        x.close()
        raise
    # the envelope grows with the recording: only what the detection plot draws is kept
    return {"a": a, "x": x, "fs": fs, "template": template, "band": band, "dur": dur, "n_samples": len(env) * dec,
            "env": envelope_summary(env, env_rate, levels.median), "dec": dec, "env_rate": env_rate, "det_t": det_t, "score": score, "asc": asc, "redetected": redetected,
            "timings": timings}


def time_array(st, session, t_emit, c, opt, fft_workers=-1, keep=None):
    """:func:`process_array`'s second phase, from :func:`detect_array`'s state ``st``: timing and DOA of
    the associated events, fused into arrivals; closes the recording. Returns the array's
    :class:`~calib.frontend.arrayresult.ArrayResult`. keep : a dict (or None) that gets ``keep[name]`` =
    {"st": the state without the recording, "ctx": the timing layout, "loc": the located events}, from which
    :func:`retime_arrivals` re-times chosen events without detecting again, and "doa" their DOAs."""
    timings = st["timings"]
    try:
        t0 = time.perf_counter()
        ctx = _timing_context(st, session, c, opt)
        # event segments read and processed in chunks (memory bounded however long the recording)
        loc = locate_events(st["x"], ctx["starts"], ctx["setup"], ctx["locate_kw"], workers=fft_workers,
                            bank=ctx["bank"])
    finally:
        st["x"].close()
    timings["timing"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    doa = _direct_path_doa(loc, ctx["mics"], st["fs"], ctx["setup"], ctx["g"], c, opt, st["a"].get("doa_hemisphere"))
    timings["doa"] = time.perf_counter() - t0
    if keep is not None:
        keep[st["a"]["name"]] = {"st": {k: v for k, v in st.items() if k != "x"}, "ctx": ctx, "loc": loc, "doa": doa}
    return _array_result(st, ctx, loc, t_emit, c, opt, doa)


def _timing_context(st, session, c, opt):
    """The timing stage's layout of one array (:func:`time_array`): matched events ``ev_idx`` (J,), segment
    ``starts`` (J,), lag layout ``g``, spectra ``setup``, Doppler ``bank`` (or None) and locate's keywords."""
    fs, band, asc, det_t = st["fs"], st["band"], st["asc"], st["det_t"]
    ev_idx = np.flatnonzero(asc["det_of"] >= 0)
    mics = np.asarray(st["a"]["mics"], float)
    g = _timing_layout(mics, band, fs, c, len(st["template"]), opt)
    starts = np.round(det_t[asc["det_of"][ev_idx]] * fs).astype(int) - g["pre"]
    setup = shared_setup(st["template"], fs, band, g["seg_len"], opt["whiten_hz"])
    # a clock drift δ disperses a linear sweep's group delay by 2|δ|T, broadening the pulse once that
    # exceeds a pulse width; the association's scale bounds |δ| (it also carries the trend of the
    # propagation delays, so only as an upper bound on the measured broadening)
    # a source moving during the sweep stretches it by 1 + ṙ/c alike (events.csv vel_x/y/z: |ṙ| ≤ |v|)
    bank = _event_bank(st["template"], setup, band, session["events"], ev_idx, c)
    # with the Doppler bank only the mismatch of its step smears the sweep
    stretch = abs(asc["scale"] - 1.0) + (_max_speed(session["events"]) / c if bank is None else
                                         STRETCH_STEP_PULSES / (st["dur"] * (band[1] - band[0])))
    smear_max = int(round(max(0.0, 2 * stretch * st["dur"] - g["pulse"]) * fs))
    return {"ev_idx": ev_idx, "mics": mics, "g": g, "starts": starts, "setup": setup, "bank": bank,
            "locate_kw": {**g["locate_kw"], "smear_max": smear_max, "own_phase": bank is not None}}


def _array_result(st, ctx, loc, t_emit, c, opt, doa=None):
    """DOAs (unless given: ``doa``, :func:`_direct_path_doa`'s dict) and fused arrivals of the located events
    ``loc`` (:func:`locate_events`): the array's :class:`~calib.frontend.arrayresult.ArrayResult`."""
    a, fs, asc, timings = st["a"], st["fs"], st["asc"], st["timings"]
    ev_idx, mics, g = ctx["ev_idx"], ctx["mics"], ctx["g"]
    if doa is None:
        t0 = time.perf_counter()
        doa = _direct_path_doa(loc, mics, fs, ctx["setup"], g, c, opt, a.get("doa_hemisphere"))
        timings["doa"] = time.perf_counter() - t0
    # mics split between paths: fused on the earliest group, for a static source only (a moving one's own carrier
    # phase per event lets mics slip a carrier period either side of the truth: moving seed 11, 3 + 3 mics 845 µs
    # apart around it, the earliest group 415 µs early)
    fused = _fuse_arrivals(loc, ctx["starts"], mics, doa, asc, t_emit, ev_idx, st["redetected"], fs, c, opt,
                           g["half"], g["pulse"] if ctx["bank"] is None else None)
    warnings = doa["warnings"] + fused["warnings"]
    if doa["normal"] is not None and a.get("doa_hemisphere") is None:
        warnings.append("planar array without doa_hemisphere: the DOA's side of the mic plane is a guess")
    if asc["ambiguous"]:
        warnings.append("association ambiguous: another alignment of the events explains as many detections")
    return ArrayResult(
        name=a["name"], fs=fs, n_samples=int(st["n_samples"]), channels=len(mics), phase=loc["phase"],
        env=st["env"], env_rate=st["env_rate"], det_t=st["det_t"], det_score=st["score"], assoc=asc, ev_idx=ev_idx,
        **{k: fused[k] for k in FUSED_KEYS}, u=doa["u"], doa_power=doa["power"], redetected=st["redetected"],
        stretch=loc["stretch"], ambiguous_plane=doa["normal"] if a.get("doa_hemisphere") is None else None,
        has_doa=doa["kind"] != "single", doa_axis=doa["axis"], warnings=warnings,
        timings=timings)


SPEED_SLACK = 0.1   # m/s: how much faster than its speed at the sweep start a robot may be during it (0.3 m/s² for
                    # 0.3 s) plus the velocity's noise
STRETCH_STEP_PULSES = 0.25   # Doppler bank spacing: a mismatch of half a step smears the pulse by 1/8 of its width
                             # (2 Δε T / 2 = this × pulse / 2), where the shift stays linear in it (β Δε)


def _event_bank(template, setup, band, events, ev_idx, c):
    """:func:`_doppler_bank` with each event's bound on |ε| (|ṙ| ≤ its speed, + SPEED_SLACK and half a step)
    as a third element; None for a robot that stops."""
    bank = _doppler_bank(template, setup, band, _max_speed(events), c)
    if bank is None:
        return None
    speed = np.linalg.norm(event_velocities(events), axis=1)[ev_idx]
    return (*bank, (speed + SPEED_SLACK) / c + 0.5 * (bank[1][1] - bank[1][0]))


def _doppler_bank(template, setup, band, vmax, c):
    """:func:`timing.stretch_bank` over ± STRETCH_MARGIN × ``vmax``/c (the largest speed of events.csv's
    velocities), a step of STRETCH_STEP_PULSES pulse widths of smear; None at 0 (a robot that stops)."""
    if vmax <= 0:
        return None
    dur = len(template) / setup["fs"]
    step = STRETCH_STEP_PULSES / ((band[1] - band[0]) * dur)
    n = int(np.ceil(STRETCH_MARGIN * vmax / c / step))
    return stretch_bank(template, setup, step * np.arange(-n, n + 1))


def _max_speed(events):
    """The largest source speed during a sweep (m/s) from events.csv's optional velocity columns; 0 without."""
    v = event_velocities(events)
    return float(np.max(np.linalg.norm(v, axis=1))) if v is not None and len(v) else 0.0


STRETCH_MARGIN = 1.25   # the Doppler bank spans ± this × the largest |v|/c of the events


def _reference_sweep_times(a, session, c, opt, beta):
    """(meta doa_time_s, stretch_time_s) of a source moving during the sweep: when the DOA looks at it
    (:func:`timing.doa_time`) and when the range rate that moves the arrival is taken (t*,
    :func:`timing.sweep_time`), at the rate and timing settings of array ``a`` (the reference), as
    :func:`_reference_beta`."""
    fs = int(read_header(a).samplerate)
    template = chirp_template(session["chirp"], fs)
    band = chirp_band(session["chirp"], template, fs)
    g = _timing_layout(np.asarray(a["mics"], float), band, fs, c, len(template), opt)
    setup = spectra_setup(template, fs, band, g["seg_len"], opt["whiten_hz"])
    return (doa_time(template, setup),
            sweep_time(template, fs, band, g["locate_kw"], g["pre"], g["seg_len"], opt["whiten_hz"], beta))


MOTION_MODEL_ERROR = 0.2   # the shift model's error, a fraction of the shift: arrival errors against β ṙ/c had
                           # slopes 0.91-1.13 and ~100-150 µs scatter on the moving preset (seed 0, 0.5 m/s)
MOTION_MODEL_ERROR_RETIMED = 0.1   # ... with the stretches predicted from the geometry (retime_arrivals): TDOA-M
                                   # errors 0.06 of the RMS shift (moving 0, 2-4: 21-58 µs), 90 % within 0.1


def motion_sd(events, c, beta, fraction=MOTION_MODEL_ERROR):
    """The TDOA error (s) a moving source's shift leaves after its correction: √2 × ``fraction`` × the RMS
    shift β ε of a range rate of |v|/√3 (a random direction), added to the frontend's sigma_tdoa."""
    v = event_velocities(events)
    eps = np.linalg.norm(v, axis=1) / np.sqrt(3) / c
    return float(np.sqrt(2) * fraction * beta * np.sqrt(np.mean(eps ** 2)))


def _reference_beta(a, session, c, opt):
    """β (:func:`timing.drift_bias`): a property of the chirp and of this estimator, at the rate and with
    the timing settings of array ``a`` (the reference). Needs the session only, not the array's results."""
    fs = int(read_header(a).samplerate)
    template = chirp_template(session["chirp"], fs)
    band = chirp_band(session["chirp"], template, fs)
    g = _timing_layout(np.asarray(a["mics"], float), band, fs, c, len(template), opt)
    return drift_bias(template, fs, band, g["locate_kw"], g["pre"], g["seg_len"], opt["whiten_hz"])


FUSED_KEYS = ("arrival", "spread", "mic_sd", "arrival_sd", "quality", "flags", "doa_spread")


def _timing_layout(mics, band, fs, c, n_template, opt):
    """Segment and lag layout of the timing stage (samples): the DOA gate (``flat`` + ``taper``), the mic
    lag half-width ``half``, the first lag searched ``lo``, the lead ``pre`` before the detection, the
    segment length, and :func:`timing.locate`'s keyword arguments."""
    aperture = np.max(np.linalg.norm(mics - mics.mean(axis=0), axis=1)) / c
    pulse = 1.0 / (band[1] - band[0])
    half = int(np.ceil((aperture + 0.5 * pulse) * fs))  # a mic's lag vs the array's: aperture + half a pulse
    flat, taper = half + int(np.ceil(opt["gate_pulses"] * pulse * fs)), int(np.ceil(2 * pulse * fs))
    lo = flat + taper + half + 2  # first lag searched: the DOA gate still fits in the segment before it
    # the direct path may precede the detection (the strongest peak, maybe a reflection) by max_distance / c;
    # a little more for the noise floor
    pre = lo + int(round((opt["max_distance"] / c + NOISE_LEAD_S) * fs))
    after = int(round(opt["search_after"] * fs))
    locate_kw = {"lo": lo, "hi": pre + after, "half_width": half, "snr_factor": opt["onset_snr"],
                 "min_ratio": opt["onset_min_ratio"], "gate": flat + taper}
    max_lag = pre + after + flat + taper + half + 4  # largest lag locate() looks at
    seg_len = max_lag + n_template + int(np.ceil(opt["max_drift"] * n_template)) + 4
    return {"pulse": pulse, "half": half, "flat": flat, "taper": taper, "pre": pre, "seg_len": seg_len,
            "locate_kw": locate_kw}


def _direct_path_doa(loc, mics, fs, setup, g, c, opt, hemisphere):
    """SRP-PHAT DOA from the gated direct path, the gate ended before the first strong reflection: what
    the array's geometry can measure (:func:`calib.frontend.doa.mic_geometry`): the full direction (3-D),
    up to the mirror image across the mic plane (planar without a hemisphere), a unit vector on the cone
    of the measured angle to the axis (linear arrays, 2-mic pairs; ``axis`` set), nothing (single mic).
    Returns u (J, 3), power (J,), the planar normal or None, the axis or None, the geometry kind, the
    gate's right edge gap (J,) samples, and warnings."""
    n_pulse = int(np.ceil(g["pulse"] * fs))
    gap = np.where(loc["reflection"] >= 0, loc["reflection"] - loc["dp"] - n_pulse - g["taper"], g["flat"])
    right = np.clip(gap, g["half"], g["flat"])
    n = len(loc["dp"])
    kind, vec = mic_geometry(mics)
    out = {"normal": None, "axis": None, "kind": kind, "gap": gap, "warnings": []}
    if kind == "single":
        return {**out, "u": np.zeros((n, 3)), "power": np.full(n, np.nan),
                "warnings": ["1 mic: no DOA; position and clock from the TDOAs only"]}
    g_spec, g_freqs, g_w = gated_spectra(loc["r"], loc["r_lo"], fs, setup, loc["dp"], g["flat"], g["taper"],
                                         loc["phase"], right)
    if kind == "linear":
        cos_t, power = srp_cone(g_spec, mics, vec, g_freqs, c, g_w)
        return {**out, "u": cone_vectors(vec, cos_t), "power": power, "axis": vec}
    sset = srp_setup(mics, g_freqs, c, opt["grid_deg"], hemisphere)
    u, power = srp_doa(g_spec, sset, g_w)
    return {**out, "u": u, "power": power, "normal": sset["planar_normal"],
            "band_sd": band_scatter(g_spec, sset, u, g_w)}


def _fuse_arrivals(loc, starts, mics, doa, asc, t_emit, ev_idx, redetected, fs, c, opt, half, pulse=None):
    """Mic times referred to the array origin and fused into one arrival per event, with their spreads,
    doubts (flags), quality and DOA spread; an array whose direct path is often weaker than a reflection is
    flagged occluded. pulse : s, the pulse width 1 / B: mics more than PATH_GAP_PULSES of it apart are on
    different paths (:func:`timing.earliest_path_group`). Returns a dict with FUSED_KEYS and ``warnings``."""
    u, val = doa["u"], loc["value"]
    t_mic = starts[:, None] / fs + loc["tau"]  # (J, M) local seconds
    good = val >= opt["min_mic_quality"] * np.max(val, axis=1, keepdims=True)
    t_org = np.where(good, t_mic + (u @ mics.T) / c, np.nan)
    arrival, spread, fused = fuse_times(t_org, path_gap=None if pulse is None else PATH_GAP_PULSES * pulse)
    mic_sd = spread * np.sqrt(np.maximum(np.sum(np.isfinite(t_org), axis=1), 1))  # one mic's spread
    gcc_quality = np.nanmedian(np.where(good, val, np.nan), axis=1)
    doa_sd = doa_spread(t_org - arrival[:, None], u, mics, c, doa["normal"], doa["axis"])
    if "band_sd" in doa:   # the larger of the two estimates of the DOA's error: the mics' misfit of one plane
        doa_sd = np.fmax(doa_sd, doa["band_sd"])   # wave, and the band's (a reflection a pulse behind)
    reasons = arrival_flags(loc, starts, arrival, spread, asc, t_emit, ev_idx, redetected, doa["gap"] < half,
                            fs, opt)
    warnings = []
    n_weak = sum("weak_direct" in r for r in reasons)
    if n_weak >= OCCLUDED_FRACTION * len(reasons):
        # an array in line of sight sees its direct path as the strongest peak in most events; here a
        # reflection dominates often, so the arrivals where no weak direct path was found are suspect too
        warnings.append(f"direct path weaker than a reflection in {n_weak} of {len(reasons)} events: line of "
                        "sight probably blocked (occluded array); its arrivals and DOAs are unreliable")
        for r in reasons:
            r.append("occluded")
    e = t_emit[ev_idx] - t_emit[0]
    lag = c * (arrival - (asc["offset"] + asc["scale"] * e))
    clean = np.array([not any(x in TIMING_DOUBTS for x in r) for r in reasons], bool)
    res = np.where(fused, t_org - arrival[:, None], np.nan)  # a mic the fusion left out is not the arrival's noise
    arrival_sd, _ = claimed_sd(res, u, mics, c, lag, e, clean, loc["interference"])
    return {"arrival": arrival, "spread": spread, "mic_sd": mic_sd, "arrival_sd": arrival_sd,
            "quality": arrival_quality(gcc_quality, reasons), "flags": reasons, "doa_spread": doa_sd,
            "warnings": warnings}


def _gate(res, hw):
    """``res`` (:func:`timing.locate`) with only the lags the DOA gate uses (± ``hw`` around the direct path)
    of its correlation ``r``, never a chunk-sized array."""
    idx = (res["dp"] - hw - res["r_lo"])[:, None] + np.arange(2 * hw + 1)
    return {**res, "r": np.take_along_axis(res["r"], idx[:, None, :], axis=-1), "r_lo": res["dp"] - hw}


SEARCH_COARSE = 3   # the first pass's Doppler search: every 3rd row, then around the best (the re-timing pass
                    # sets the rows of every array the first solve places)
TIMING_CHUNK_BYTES = 128e6  # working memory of one chunk of events in the timing stage (segments + FFTs)


def locate_events(x, starts, setup, locate_kw, chunk_bytes=TIMING_CHUNK_BYTES, workers=-1, bank=None, rows=None):
    """:func:`timing.locate` on all events, a chunk of events at a time (memory bounded by ``chunk_bytes``).

    x : (M, N) recording (ndarray or :class:`signals.ArrayAudio`). starts : (J,) int segment starts.
    Each chunk's whitened and plain (onset) spectra come from :func:`timing.segment_spectra`. The carrier
    phase is estimated on the first chunk (all events when they fit in one) and used for every chunk, so
    all of the array's events share it. Returns locate's dict with the per-event arrays concatenated; its
    ``r`` holds only the lags ``r_lo[j] .. r_lo[j] + 2 gate`` of event j (``r_lo`` (J,) = dp − gate).
    workers : threads of the segments' FFTs (:func:`timing.segment_spectra`). bank : (factors, stretches[,
    bound (J,)]) of :func:`_event_bank` (a source moving during the sweep): each event is timed against the
    template stretched by its best-matching ε (:func:`timing.matched_stretch`, |ε| ≤ bound), returned as
    ``stretch`` (J,); else 0. rows : (J,) int, the bank's row of each event given (a stretch predicted from
    the geometry, :func:`retime_arrivals`) instead of searched.
    """
    m = x.shape[0]
    per_event = 32 * m * setup["nfft"]  # bound on a segment + its FFT + both band spectra, per event
    n = max(1, int(chunk_bytes // per_event))
    parts, sizes, phase, own = [], [], locate_kw.get("phase"), locate_kw.get("own_phase", False)
    for j0 in range(0, max(len(starts), 1), n):
        chunk = starts[j0 : j0 + n]
        c, c_plain = segment_spectra(x, chunk, setup, plain=True, workers=workers)  # (J_c, M, Fb) each
        stretch, onset = np.zeros(len(chunk)), None
        if bank is not None:
            k, onset = (np.asarray(rows[j0 : j0 + n], int), None) if rows is not None else matched_stretch(
                c_plain, setup, bank[0], locate_kw["lo"], locate_kw["hi"], locate_kw["snr_factor"],
                locate_kw["min_ratio"], stretches=bank[1], bound=bank[2][j0 : j0 + n] if len(bank) > 2 else None,
                coarse=SEARCH_COARSE)
            c *= bank[0][k][:, None, :]
            c_plain *= bank[0][k][:, None, :]
            stretch = bank[1][k]
        # (the searched rows' onset envelope: matched_stretch's, not computed again)
        res = locate(c, setup, **{**locate_kw, "phase": phase}, c_onset=c_plain, onset_env=onset)
        res["stretch"] = stretch
        onset_env = res.pop("onset_env")   # (J_c, lags): searched again by retime_earlier, not kept
        # a weak direct path before the timed arrival (a reflection): timed again on it (frontend.nlos); not
        # for a moving source, whose paths each have their own stretch (the subtraction's pulse model fails)
        res, again = (res, None) if bank is not None else retime_earlier(res, c, c_plain, setup,
                                                                          {**locate_kw, "phase": phase}, onset_env)
        res = _gate(res, locate_kw.get("gate", 0))
        if again is not None:
            res = _merge_events(res, _gate(again, locate_kw.get("gate", 0)), again["events"], len(res["dp"]))
        parts.append(res)
        sizes.append(len(chunk))
        phase = None if own else parts[0]["phase"]
    out = dict(parts[0])
    for key, v in parts[0].items():
        if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == sizes[0] and (key != "phase" or own):
            out[key] = np.concatenate([p[key] for p in parts])
    return out


NOISE_LEAD_S = 0.010     # the timing segment starts this much before the earliest possible direct path
WEAK_DIRECT = 0.35       # direct path below this × the strongest peak: flagged "weak_direct"
EARLY_ONSET_S = 0.030    # direct path more than this before the strongest peak: flagged "early_onset"
LOW_SNR = 2.0            # direct path below this × the onset threshold: flagged "low_snr"
SPREAD_FACTOR = 5.0      # arrival standard error above this × the array's median: flagged "mic_spread"
DOUBT_PENALTY = 0.5      # each doubt halves an arrival's quality
OCCLUDED_FRACTION = 0.3  # "weak_direct" in at least this fraction of an array's events: flagged "occluded"
PATH_GAP_PULSES = 0.5    # mics' times this many pulse widths apart are on different paths (two resolve ~1 / 2B apart)


def _redetect_missed(env, env_rate, det_t, score, asc, t_emit, c, opt, levels=None):
    """Events the association left without a detection: look again near their predicted arrival time at
    ``redetect_threshold`` (the window: the matched arrivals' largest deviation from the clock line, plus
    5 ms, at most ``max_distance`` / c and the association tolerance; ``levels``: the envelope's background,
    :func:`detect.background`). Updates ``asc`` in place.
    Returns (det_t, score, redetected (K,) bool per event)."""
    e = t_emit - t_emit[0]
    pred = asc["offset"] + asc["scale"] * e
    redetected = np.zeros(len(t_emit), bool)
    missed = np.flatnonzero(asc["det_of"] < 0)
    if not missed.size or opt["redetect_threshold"] >= opt["threshold"]:
        return det_t, score, redetected
    got = np.flatnonzero(asc["det_of"] >= 0)
    dev = np.max(np.abs(det_t[asc["det_of"][got]] - pred[got]))
    half = min(dev + 0.005, opt["max_distance"] / c, asc["tolerance"])
    idx, sc = redetect(env, env_rate, pred[missed], half, opt["redetect_threshold"], levels=levels)
    taken = det_t[asc["det_of"][got]]
    for j, q, s in zip(missed, idx, sc):
        t = refine_peak(env, q) / env_rate if q >= 0 else np.nan
        if q < 0 or np.any(np.abs(taken - t) < 0.5 * np.min(np.abs(np.diff(t_emit)), initial=np.inf)):
            continue
        det_t, score = np.r_[det_t, t], np.r_[score, s]
        asc["event_of"] = np.r_[asc["event_of"], j]
        asc["det_of"][j] = len(det_t) - 1
        asc["n_matched"] += 1
        redetected[j] = True
    return det_t, score, redetected


def arrival_flags(loc, starts, arrival, spread, asc, t_emit, ev_idx, redetected, doa_reflection, fs, opt):
    """Why each arrival is doubtful: (J,) lists of reason strings (empty = no doubt). See docs/frontend.md.

    Clock-track check: ``arrival − (offset + scale·(t_emit − t_emit[0]))`` is the propagation delay up to a
    constant; an arrival whose residual differs from the median of its (up to 4) nearest matched
    neighbours' by more than ``track_tol`` disagrees with the array's clock track ("track").
    """
    j = len(ev_idx)
    reasons = [[] for _ in range(j)]
    lead = (loc["strongest"] - loc["dp"]) / fs
    res = arrival - (asc["offset"] + asc["scale"] * (t_emit[ev_idx] - t_emit[0]))
    med_spread = np.nanmedian(spread) if np.any(np.isfinite(spread)) else np.nan
    for k in range(j):
        r = reasons[k]
        if redetected[ev_idx[k]]:
            r.append("redetected")
        if loc["ratio"][k] < WEAK_DIRECT:
            r.append("weak_direct")
        if lead[k] > EARLY_ONSET_S:
            r.append("early_onset")
        if loc["snr"][k] < LOW_SNR * opt["onset_snr"]:
            r.append("low_snr")
        if np.isfinite(spread[k]) and spread[k] > max(SPREAD_FACTOR * med_spread, 2e-6):
            r.append("mic_spread")
        if doa_reflection[k]:
            r.append("doa_reflection")
        nb = np.argsort(np.abs(np.arange(j) - k))[1:5]
        if nb.size >= 2 and abs(res[k] - np.median(res[nb])) > opt["track_tol"]:
            r.append("track")
    return reasons


def arrival_quality(gcc_quality, reasons):
    """Per-arrival quality in [0, 1]: the median normalised GCC carrier peak over the mics (~1 for one
    clean path) × ``DOUBT_PENALTY`` per doubt (:func:`arrival_flags`; ``DOA_ONLY_DOUBTS`` concern the DOA
    only)."""
    n = np.array([sum(x not in DOA_ONLY_DOUBTS for x in r) for r in reasons])
    return np.clip(gcc_quality, 0.0, 1.0) * DOUBT_PENALTY ** n


DOA_SPREAD_FACTOR = 30.0  # a DOA whose own spread exceeds this × the session's median is doubtful ("doa_spread"): in
                          # the RMS that sets the session's DOA sigma it would weigh as much as 900 typical rows


def flag_nlos(results, events, shift, c):
    """Add the doubt "nlos" to every arrival late against its array's own range track along the odometry
    (:func:`calib.frontend.nlos.late_arrivals_many`, every array's track fitted together: a reflection-only
    arrival, the direct path blocked) and halve its quality (in place). Returns the results with each arrival's lateness as ``late`` (s; NaN: not judged)
    and the track's clock drift as ``track_drift`` (NaN: not judged)."""
    t_emit = events["t_emit"].to_numpy(float)
    odom = events[["odom_x", "odom_y", "odom_z"]].to_numpy(float)
    vel = event_velocities(events)
    out = {}
    judged = late_arrivals_many([(np.asarray(r["arrival"], float), t_emit[r["ev_idx"]] - t_emit[0], odom[r["ev_idx"]],
                                  None if vel is None else vel[r["ev_idx"]]) for r in results.values()], c, shift)
    for (name, r), ev in zip(results.items(), judged):
        j = r["ev_idx"]
        out[name] = r.replace(late=ev["late"], track_drift=ev["drift"])
        for k in np.flatnonzero(ev["nlos"]):
            r["flags"][k].append("nlos")
            r["quality"][k] *= DOUBT_PENALTY
        n = int(ev["nlos"].sum())
        if n:
            r["warnings"].append(f"{n} of {len(j)} arrivals are late against the array's range track along the "
                                 "odometry by more than a direct path can be (reflection only: line of sight "
                                 "blocked, flagged nlos)")
        if ev["scale"] > TRACK_SCALE_MAX:
            r["warnings"].append(f"the arrivals follow no range track along the odometry (robust scatter "
                                 f"{1e3 * ev['scale']:.1f} ms about the best one): reflection-only arrivals are not "
                                 "judged (is the odometry in metres, and this session's?)")
        if ev["early"] >= max(3, 0.1 * len(j)):
            r["warnings"].append(f"{ev['early']} arrivals are early against the array's range track: most of its "
                                 "arrivals may be reflections (line of sight blocked)")
    return out


MOVING_DOA_SPREAD_DEG = 10.0  # an array's median DOA spread above this: its mics disagree with any one plane wave
                              # (0.3-2° in the controlled rooms; 17 and 76° for 2 of 4 arrays of a robot moving
                              # at 0.5 m/s, preset moving seed 0, without velocities)


def warn_moving(results, events):
    """Warn (every array's warnings) when the DOA spreads say the source moved during the sweep — its
    stretch smears every mic's pulse — and events.csv gives no velocities to correct for it: at least half
    of the arrays with DOAs have a median spread above MOVING_DOA_SPREAD_DEG (one occluded array alone
    does not make it)."""
    if event_velocities(events) is not None:
        return
    med = [float(np.degrees(np.nanmedian(r["doa_spread"]))) for r in results.values()
           if r["has_doa"] and np.any(np.isfinite(r["doa_spread"]))]
    high = [m for m in med if m > MOVING_DOA_SPREAD_DEG]
    if med and len(high) >= 0.5 * len(med):
        text = (f"the DOAs of {len(high)} of {len(med)} arrays disagree with any plane wave (median spreads "
                f"{', '.join(f'{m:.0f}' for m in high)}° > {MOVING_DOA_SPREAD_DEG:g}°): did the source move during "
                "the sweeps? events.csv vel_x, vel_y, vel_z let calib correct for it")
        for r in results.values():
            r["warnings"].append(text)


def flag_no_direct(results):
    """Add the doubt "nlos" to every arrival whose own waveform shows no direct path
    (:func:`calib.frontend.nlos.no_direct_path`, a reflection-only arrival too little late for its range track) and
    halve its quality (in place)."""
    for r in results.values():
        ks = [k for k in np.flatnonzero(no_direct_path(r["flags"])) if "nlos" not in r["flags"][k]]
        for k in ks:
            r["flags"][k].append("nlos")
            r["quality"][k] *= DOUBT_PENALTY
        if ks:
            r["warnings"].append(f"{len(ks)} of {len(r['flags'])} arrivals show no direct path (a weak onset and mics "
                                 "that agree with no one plane wave: reflection only, flagged nlos)")


def flag_doa_spread(results):
    """Add the doubt "doa_spread" to every arrival whose DOA spread (:func:`doa_spread`) exceeds
    ``DOA_SPREAD_FACTOR`` × the median over the session's DOAs without doubts (in place; the median over
    all of them if none is clean). The mics of such a DOA disagree with any one plane wave far beyond
    the session's typical DOA: several paths of similar strength (an occluded array's DOAs reached
    77–151° in one session while the others' median was 0.3°). The session's DOA sigma is an RMS over the
    rows without doubts, which one such row (a thousand typical rows' worth) would otherwise decide.
    The median is over all arrays: an array whose DOAs are all that poor does not set its own scale."""
    spreads, clean = [], []
    for r in results.values():
        if r["has_doa"]:
            spreads.append(np.asarray(r["doa_spread"], float))
            clean.append([not any(x in DOA_DOUBTS for x in f) for f in r["flags"]])
    if not spreads:
        return
    v, ok = np.concatenate(spreads), np.concatenate(clean).astype(bool)
    pos = np.isfinite(v) & (v > 0)
    ref = v[pos & ok] if np.any(pos & ok) else v[pos]
    if not ref.size:
        return
    limit = DOA_SPREAD_FACTOR * float(np.median(ref))
    for r in results.values():
        if r["has_doa"]:
            for k in np.flatnonzero(np.nan_to_num(np.asarray(r["doa_spread"], float)) > limit):
                r["flags"][k].append("doa_spread")


IN_PLANE_FLOOR = 1e-12   # least σ_v (the in-plane part's std) in doa_spread's floor √σ_v of |u·n|


def doa_spread(res, u, mics, c, normal=None, axis=None):
    """Internal-consistency standard deviation (rad, per tangent axis) of each DOA.

    res : (J, M) residuals of the mic times referred to the origin (s, NaN = unused). For the plane-wave
    fit ``t_m = t_0 − u·m/c`` the covariance of ``u`` is ``c² σ² P S⁺ P`` (S the scatter of the mic
    positions, P the projector orthogonal to u, σ the residual spread less the wavefront curvature:
    :func:`_doa_noise_var`). A planar array (unit ``normal``)
    measures only the in-plane part ``v`` of ``u``; the normal part ``√(1 − |v|²)`` follows with the
    Jacobian ``I − n vᵀ / |u·n|``, which grows as the source nears the array's plane (``|u·n|`` floored at
    ``√σ_v``, where the linearisation ends). A linear array (unit ``axis``) measures cos θ = u·axis with
    std ``c σ / √(Σ_m d_m²)`` (d_m the mics' coordinates along the axis; 2 dof of the fit: NaN for a pair),
    in the cone factor's units. Biases common to all mics are invisible here. Returns (J,); NaN for
    fewer than 3 mics.
    """
    ok = np.isfinite(res)
    n = ok.sum(axis=1)
    if len(mics) < 3:
        return np.full(len(u), np.nan)
    d = mics - mics.mean(axis=0)
    if axis is not None:
        sig2 = (np.where(ok, res, 0.0) ** 2).sum(axis=1) / np.maximum(n - 2, 1)  # t_0 and θ
        return c * np.sqrt(sig2 / np.sum((d @ np.asarray(axis, float)) ** 2))
    sig2 = _doa_noise_var(res, u, mics, c)
    floor = 0.0
    if normal is not None:
        sig_v = c * np.sqrt(sig2 * np.trace(np.linalg.pinv(d.T @ d)) / 2)
        floor = np.sqrt(np.maximum(sig_v, IN_PLANE_FLOOR))  # a DOA in the plane (doa._refine_planar: |v| > 1)
                                                              # whose mics fit exactly: no 0 / 0
    tr = np.trace(doa_covariance(u, mics, normal, floor), axis1=1, axis2=2)
    return c * np.sqrt(sig2 * tr / 2)


def _doa_noise_var(res, u, mics, c):
    """(J,) variance of one mic's time about the array model, the part that moves a DOA.

    The wavefront curvature of a near source (``near_field_fit``: ≈ 1.8 µs across a 10 cm array at 2 m) is
    symmetric about the array's centre, so it leaves the direction alone; counted as noise it made the hall's
    10 cm arrays claim 2.3× their DOA error (CHANGELOG.md, issue 9). With ≥ 5 mics the curvature is fitted
    and removed (4 dof: t_0, two angles, κ); otherwise the plane-wave spread (3 dof).
    """
    ok = np.isfinite(res)
    n = ok.sum(axis=1)
    plain = (np.where(ok, res, 0.0) ** 2).sum(axis=1) / np.maximum(n - 3, 1)
    kappa, _, s, _, _ = near_field_fit(res, u, mics, c)
    fit = np.isfinite(kappa) & (n > 4)
    return np.where(fit, s**2 * (n - 2) / np.maximum(n - 4, 1), plain)


def gated_spectra(r, r_lo, fs, setup, center, flat, taper, phase, right=None):
    """Spectra of each mic's response gated around the direct path, PHAT-normalised.

    The gate is flat from ``center − flat`` to ``center + right`` samples (wide enough for every mic's
    pulse, so the gate does not pull the pulses toward its centre, which would compress the inter-mic
    delays and bias the DOA) and rolls off over ``taper`` samples on each side. ``right`` (J,) ≤ ``flat``
    ends it before the first strong reflection (default ``flat``: symmetric).

    r : (J, M, T) analytic correlation on lags r_lo... center : (J,) int lags.
    Returns g (J, M, F'), freqs (F',), weights (F',).
    """
    half_width = flat + taper
    width = 2 * half_width + 1
    nfft = int(2 ** np.ceil(np.log2(4 * width)))  # dense frequency sampling: per-bin PHAT is then accurate
    idx = (np.asarray(center) - half_width - r_lo)[:, None] + np.arange(width)  # (J, W)
    ph = np.asarray(phase)[:, None, None] if np.ndim(phase) else phase   # (J,): each event's own phase
    seg = np.real(np.take_along_axis(r, idx[:, None, :], axis=-1) * np.exp(-1j * ph))
    right = np.full(len(idx), flat) if right is None else np.asarray(right)
    o = np.arange(width) - half_width  # offset from the centre
    edge = np.where(o[None, :] < 0, flat, right[:, None])  # (J, W) end of the flat part on each side
    past = np.abs(o)[None, :] - edge
    gate = np.where(past <= 0, 1.0, np.where(past < taper, 0.5 + 0.5 * np.cos(np.pi * past / taper), 0.0))
    seg *= gate[:, None, :]
    spec = np.fft.rfft(seg, nfft, axis=-1)
    freqs = np.fft.rfftfreq(nfft, 1 / fs)
    w = np.interp(freqs, setup["freqs"], setup["weights"] / setup["weights"].max(), left=0.0, right=0.0)
    keep = w > 0.05
    spec = spec[..., keep]
    return spec / np.maximum(np.abs(spec), 1e-30), freqs[keep], w[keep]


def _tables(session, results, ev_ids, beta):
    ref = session["reference_array"]
    names = [a["name"] for a in session["arrays"]]
    arr = {}
    for name, r in results.items():
        late = r.get("late", np.full(len(r["ev_idx"]), np.nan))
        arr[name] = {int(ev_ids[j]): (r["arrival"][k], r["quality"][k], _flag_text(r["flags"][k], doa=False), late[k])
                     for k, j in enumerate(r["ev_idx"])}
    tm, ts, doa = [], [], []
    for name in names:
        for e, (t, q, f, lt) in arr[name].items():
            if name != ref and e in arr[ref]:
                tr, qr, fr, lr = arr[ref][e]
                tm.append((e, name, t - tr, min(q, qr), _join(fr, f), _later(lt, lr)))
        evs = sorted(arr[name])
        for e1, e2 in zip(evs[:-1], evs[1:]):
            (t1, q1, f1, l1), (t2, q2, f2, l2) = arr[name][e1], arr[name][e2]
            ts.append((name, e1, e2, t2 - t1, min(q1, q2), _join(f1, f2), _later(l1, l2)))
        r = results[name]
        for k, j in enumerate(r["ev_idx"] if r["has_doa"] else []):
            doa.append((int(ev_ids[j]), name, *r["u"][k], r["doa_power"][k], _flag_text(r["flags"][k], doa=True),
                        _row_sigma_deg(r["doa_spread"][k]) if r.doa_axis is None else np.nan,
                        arr[name][int(ev_ids[j])][3]))
    est = noise_estimates(results)
    est = {k: v for k, v in est.items() if k in ("sigma_tdoa", "sigma_doa_deg", "sigma_arrival_per_array")}
    meta = {"speed_of_sound": session["speed_of_sound"], "reference_array": ref, "arrays": names,
            **{k: v for k, v in est.items() if v is not None}, **session["noise"], "chirp_drift_bias": beta,
            "tdoa_shared_arrivals": True}   # TDOA-M and TDOA-S are differences of one arrival per (array, event)
    # which sigmas are the frontend's own (spread-based) figures rather than the user's priors:
    # the estimator's noise="auto" then re-estimates the weights from the residuals
    meta["sigmas_estimated"] = sorted(k for k, v in est.items() if v is not None and k not in session["noise"]
                                      and k != "sigma_arrival_per_array")   # (relative weights, not a sigma key)
    planes = {n: [float(v) for v in results[n].ambiguous_plane] for n in names
              if results[n].ambiguous_plane is not None}
    if planes:
        meta["doa_mirror_normals"] = planes
    axes = {n: [float(v) for v in results[n].doa_axis] for n in names if results[n].doa_axis is not None}
    if axes:  # linear arrays and 2-mic pairs: their doa.csv rows are on the cone about this axis
        meta["doa_axes"] = axes
    return {
        "meta": meta,
        "events": session["events"].copy(),
        "tdoa_m": pd.DataFrame(tm, columns=["event", "array", "tdoa", "quality", "flag", "late_s"])
        .astype({"event": int}),
        "tdoa_s": pd.DataFrame(ts, columns=["array", "from_event", "to_event", "tdoa", "quality", "flag", "late_s"])
        .astype({"from_event": int, "to_event": int}),
        "doa": pd.DataFrame(doa, columns=["event", "array", "ux", "uy", "uz", "quality", "flag", "sigma_deg",
                                          "late_s"]).astype({"event": int}),
    }


def _row_sigma_deg(sd):
    """doa.csv's ``sigma_deg`` of a row from its spread (rad): empty (NaN) where there is none to give (fewer
    than 4 mics leave the plane-wave fit no residual). Linear arrays' rows get none (their spread is the
    std of cos θ, not an angle)."""
    return float(np.degrees(sd)) if np.isfinite(sd) and sd > 0 else np.nan


TIMING_DOUBTS = ("redetected", "weak_direct", "early_onset", "low_snr", "mic_spread", "track", "occluded", "nlos")
DOA_DOUBTS = ("weak_direct", "low_snr", "doa_reflection", "doa_spread", "mic_spread", "occluded", "nlos")
DOA_ONLY_DOUBTS = ("doa_reflection", "doa_spread")  # no bearing on the arrival time (nor its quality)


def _flag_text(reasons, doa):
    """The ``flag`` column: the doubts that concern a timing (or a DOA) row, joined by '+'; '' = none."""
    keep = DOA_DOUBTS if doa else TIMING_DOUBTS
    return "+".join(x for x in reasons if x in keep)


def _later(a, b):
    """``late_s`` of a row built from two arrivals: the later one's (NaN when neither was judged)."""
    return float(np.nanmax([a, b])) if np.isfinite(a) or np.isfinite(b) else np.nan


def _join(a, b):
    """Flags of a row built from two arrivals (union, order kept)."""
    parts = [x for x in (a.split("+") if a else []) + (b.split("+") if b else [])]
    return "+".join(dict.fromkeys(parts))


def noise_estimates(results):
    """Measurement noise of the features, from the spread between each array's mics (docs/frontend.md).

    sigma_tdoa: √2 × the RMS over arrivals of ``arrival_sd`` (a TDOA is a difference of two arrivals; RMS,
    not median: the errors are heavy-tailed and the estimator takes sigma as a standard deviation): the
    differential, later-path and near-field parts of :mod:`calib.frontend.noise`. The standard error of the
    plane-wave mean is kept as ``sigma_tdoa_lower`` (diagnostics only). Only arrivals without doubts
    (``flag`` empty) count: the sigmas describe the unflagged rows; flagged ones are doubtful by definition
    (all, if none is clean).
    sigma_arrival_per_array: {array: the RMS of its own arrivals' ``arrival_sd``} (same rules; arrays with
    nothing to estimate from left out): boards of different makes in one session time their arrivals
    unequally well (a 2-mic pair's scatter 6× a 6-mic circle's, mixed preset), and the estimator weights
    their TDOA rows relative to one another by it (docs/method.md "Per-array arrival sigmas").
    sigma_doa_deg: the RMS of the rows' ``doa_spread`` (:func:`doa_spread`: plane-wave fit covariance, per
    tangent axis, planar arrays with the elevation Jacobian; or the sub-band scatter
    :func:`calib.frontend.doa.band_scatter` where larger). None where there is nothing to estimate from.
    """
    dsd = _clean_rms(results.values(), "doa_spread", DOA_DOUBTS)
    own = {name: _clean_rms([r], "arrival_sd", TIMING_DOUBTS) for name, r in results.items()}
    return {"sigma_tdoa": _clean_rms(results.values(), "arrival_sd", TIMING_DOUBTS, np.sqrt(2)),
            "sigma_doa_deg": None if dsd is None else float(np.degrees(dsd)),
            "sigma_arrival_per_array": {k: v for k, v in own.items() if v is not None} or None,
            "sigma_tdoa_lower": _clean_rms(results.values(), "spread", TIMING_DOUBTS, np.sqrt(2))}


def _clean_rms(results, key, doubts, scale=1.0):
    """``scale`` × the RMS of ``key`` over the arrivals of ``results`` (per-array result dicts) without any of
    ``doubts`` (all arrivals, if none is clean); finite positive values only; None when there are none."""
    results = list(results)
    v = np.concatenate([r[key] for r in results])
    clean = np.concatenate([[not any(x in doubts for x in f) for f in r["flags"]] for r in results])
    ok = np.isfinite(v) & (v > 0)
    v = v[ok & clean] if np.any(ok & clean) else v[ok]
    return float(scale * np.sqrt(np.mean(v**2))) if v.size else None


def _diagnostics(session, results, ev_ids, beta, elapsed):
    arrays = {}
    total_dur = 0.0
    for a in session["arrays"]:
        r = results[a["name"]]
        asc = r["assoc"]
        dur = r["n_samples"] / r["fs"]
        total_dur = max(total_dur, dur)
        dets = []
        for k, t in enumerate(r["det_t"]):
            e = int(asc["event_of"][k])
            dets.append({"time": float(t), "score": float(r["det_score"][k]),
                         "event": int(ev_ids[e]) if e >= 0 else None})
        arrays[a["name"]] = {
            "wav": str(a["wav"]), "fs": r["fs"], "channels": r["channels"], "duration_s": dur,
            "detections": dets,
            "missed_events": [int(ev_ids[j]) for j in np.flatnonzero(asc["det_of"] < 0)],
            "spurious": [d for d in dets if d["event"] is None],
            "association": {"offset_s": float(asc["offset"]), "scale": float(asc["scale"]),
                            "n_matched": int(asc["n_matched"]), "tolerance_s": asc["tolerance"],
                            "residual_rms_s": float(asc["residual_rms"]), "ambiguous": bool(asc["ambiguous"])},
            "arrival_spread_median_s": float(np.nanmedian(r["spread"])),
            # the clock drift of the array's range track along the odometry (flag_nlos; None: not judged)
            "track_drift": float(r["track_drift"]) if np.isfinite(r.get("track_drift", np.nan)) else None,
            "arrivals": [{"event": int(ev_ids[j]), "time": float(r["arrival"][k]),
                          "quality": float(r["quality"][k]), "flag": "+".join(r["flags"][k]),
                          "mic_sd_s": float(r["mic_sd"][k]), "sd_s": float(r["arrival_sd"][k]), "doa_sd_deg": float(np.degrees(r["doa_spread"][k])),
                          "late_s": float(r["late"][k]) if "late" in r else None,
                          "stretch": float(r["stretch"][k])}
                         for k, j in enumerate(r["ev_idx"])],
            "doubtful": {int(ev_ids[j]): r["flags"][k] for k, j in enumerate(r["ev_idx"]) if r["flags"][k]},
            "redetected_events": [int(ev_ids[j]) for j in np.flatnonzero(r["redetected"])],
            "chirp_phase_rad": float(estimate_phase(np.exp(1j * np.asarray(r["phase"])))),
            "warnings": r["warnings"],
            "timings_s": r["timings"],
            "_env": r["env"], "_env_rate": r["env_rate"],
            "_predicted": asc["offset"] + asc["scale"] * (session["events"]["t_emit"].to_numpy() -
                                                         session["events"]["t_emit"].iloc[0]),
        }
    return {"arrays": arrays, "chirp_drift_bias": beta, "noise_estimates": noise_estimates(results),
            "elapsed_s": elapsed, "recording_duration_s": total_dur,
            "event_ids": [int(e) for e in ev_ids]}
