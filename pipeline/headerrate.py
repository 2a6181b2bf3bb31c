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
# A clock this far (relative) from the emitter's is no crystal's (they keep ±1e-4): its samples are taken at its
# measured rate, its template mismatch (2 Doppler-bank steps) biasing the frontend's multipath checks otherwise
FAST_CLOCK = 3e-4
OUTLIER_THRESHOLD = 5.0   # the refining solve's outlier test (calibrate's default: a drift, not a geometry)
REFINE_ROUNDS = 2   # first solves that refine the rates (the second when the first moved a rate)
CLAMPED = 0.98   # an association scale this close to its search bound (× max_drift) is a fast-clock candidate
# ... unless the array's range track along the odometry (the frontend's NLOS check, frontend/nlos.py: position,
# offset and drift fitted to its direct paths) already puts its drift within a crystal's ±1e-4: the association's
# line then carries the range's trend (a source crossing a 40 m hall: 1e-3), not the clock's (warehouse 500 A6:
# association 1.0e-3, track -2.7e-5, true -2.4e-5; tracks within 1.2e-4 of the truth on its 11 arrays)
CRYSTAL_DRIFT = 1e-4
# A track that puts the drift beyond this is a candidate on its own: half FAST_CLOCK, the tracks’ error (≤ 5.3e-5 on
# dev seeds 500-501 of six presets, crystals and ±1e-3 clocks) above a crystal's 1e-4
TRACK_FAST = 0.5 * FAST_CLOCK
# An array whose detections match fewer of the events than this, and whose detections' intervals agree with fewer
# than setupcheck.CLOCK_SUPPORT of the emission intervals at any one scale, is searched at other rates ...
MATCHED_MIN = 0.8
# ... these multiples of its header's: every ratio of two common rates within ±13 % (44.1 kHz written as 48: 0.91875)
# and a grid 1.5 % apart between them (the detector finds a 0.5 s sweep within ~1 % of its rate)
SEARCH_SCALES = tuple(np.unique(np.round(np.r_[np.arange(0.87, 1.135, 0.015), 44100 / 48000, 48000 / 44100,
                                               22050 / 24000, 24000 / 22050], 5)))


def line_residuals(times, t_emit, scale, tol=MATCH_TOL):
    """(nearest event, residual s) of each detection ``times`` (sorted) against the line ``scale · t_emit + b``;
    the offset b is the mode of every (detection − predicted emission) pair, to ``tol``."""
    pred = scale * t_emit
    lags = (times[:, None] - pred[None, :]).ravel()
    bins = np.round(lags / tol).astype(np.int64)
    vals, counts = np.unique(bins, return_counts=True)
    b = float(np.median(lags[bins == vals[np.argmax(counts)]]))
    k = times[:, None] - (pred[None, :] + b)
    near = np.argmin(np.abs(k), axis=1)
    return near, k[np.arange(len(times)), near]


def refine_scale(times, t_emit, scale, tol=MATCH_TOL):
    """(scale, n matched): the straight-line fit ``time = scale · t_emit + b`` of the detections ``times`` (s,
    local clock) matched to the emission times ``t_emit`` predicted at the coarse ``scale`` (offset: the
    median residual of each detection against its nearest predicted event)."""
    times, t_emit = np.sort(np.asarray(times, float)), np.sort(np.asarray(t_emit, float))
    for _ in range(2):
        near, res = line_residuals(times, t_emit, scale, tol)
        ok = np.abs(res) < tol
        if ok.sum() < MIN_MATCHED:
            return scale, int(ok.sum())
        scale = float(np.polyfit(t_emit[near[ok]], times[ok], 1)[0])
    return scale, int(ok.sum())


def rate_corrections(session, diagnostics, threshold=8.0):
    """{array: {"header": Hz, "used": Hz, "scale", "support", "matched"}} for the arrays whose stated rate the
    chirps contradict (module doc); {} when none or when every array is off alike (events.csv's times). An
    array whose chirps the header-rate detector mostly missed (a sweep 5-10 % off its template) is searched
    at other rates (:func:`searched_scale`; ``threshold``: the detector's). Not one whose detections there
    agree with ``CLOCK_SUPPORT`` of the emission intervals at one scale, whatever the share of events it
    matched: that scale decides, off or not. The search reads the whole recording at each of
    ``SEARCH_SCALES``; a warehouse array that missed 4 of its 16 chirps behind an obstacle at 5 dB SNR (seed
    511, A9: scale 1.00035 from 53 % of the intervals) spent 0.9 s of CPU there, more than the extraction of
    all ten arrays, to find 1.00073 from 35 % (the grid does not hold the header's own rate)."""
    from calib.frontend.consistency import clock_scale
    from calib.pipeline.setupcheck import CLOCK_FAIL, CLOCK_SUPPORT, emission_times_scaled

    t_emit = session["events"]["t_emit"].to_numpy(float)
    arrays = (diagnostics or {}).get("arrays", {})
    found = {}
    for a in session["arrays"]:
        d = arrays.get(a["name"]) or {}
        if a.get("sample_rate") is not None or not d.get("fs"):
            continue   # a declared rate is the user's word
        times = np.array([x["time"] for x in d.get("detections", [])], float)
        s, support = clock_scale(times, t_emit)
        matched = sum(x.get("event") is not None for x in d.get("detections", []))
        decided = support >= CLOCK_SUPPORT   # the intervals settle the scale: off by > CLOCK_FAIL or not
        if matched < MATCHED_MIN * len(t_emit) and not decided:
            s, support, times = searched_scale(a, session, threshold)
        if not (support >= CLOCK_SUPPORT and abs(s - 1) > CLOCK_FAIL):
            continue
        s, matched = refine_scale(times, t_emit, s)
        found[a["name"]] = {"header": int(d["fs"]), "scale": s, "support": float(support), "matched": matched}
    if emission_times_scaled({n: f["scale"] for n, f in found.items()}, len(session["arrays"])):
        return {}   # the emission times, not the headers (setupcheck.clock_findings names events.csv)
    for f in found.values():
        f["used"] = nominal_rate(f["header"] * f["scale"])
    return found


def fast_clocks(session, feats, diagnostics, max_drift, skip=()):
    """Candidates for :func:`refine_rates` ({array: {"header", "used" = header, "scale": 1, "fast_clock": True}}):
    the arrays (not ``skip``, no declared rate) whose arrivals jump nowhere (``clockmodel.impossible_jumps``: a
    dropped block is no rate) and either

    - whose range track along the odometry (diagnostics ``track_drift``, the frontend's NLOS check; only a track
      its direct paths follow within ``TRACK_SCALE_MAX`` is exported) puts their drift beyond half ``FAST_CLOCK``
      (``TRACK_FAST``), wherever the association's scale sits: a range trend tilts that line by up to ~1e-3
      either way, hiding a fast clock inside the bound (paper-traj3 500 A2 at -1e-3: association -8.9e-4, track
      -1.04e-3), and ``arrival_drift`` finds no chain in a U-shaped room (ushape 500 A2 at +1e-3: track 1.08e-3);
    - or whose association's scale sits at its search bound 1 ± ``max_drift`` (the frontend's option) — a clock
      faster or slower than a crystal runs, range changes that tilt the association's line, or a clock that
      steps — whose track does not already put their drift within ``CRYSTAL_DRIFT`` and whose arrivals against
      the odometry (``setupcheck.arrival_drift``, no solve) put their drift beyond half ``FAST_CLOCK``. That
      drift is read from the arrivals in line of sight only (the rows the estimator keeps, ``estimator.screen``):
      reflection-only arrivals, 5-70 ms late in a U-shaped room, put 8e-4-1.5e-3 of drift on clocks within 1e-4
      (ushape seed 62: A2 taken at 15987 Hz).

    The first solve's drift decides (:func:`refine_rates`)."""
    clamped, tracked = {}, {}
    for a in session["arrays"]:
        d = ((diagnostics or {}).get("arrays", {}).get(a["name"]) or {})
        scale = (d.get("association") or {}).get("scale")
        if a["name"] in skip or a.get("sample_rate") is not None or scale is None or not d.get("fs"):
            continue
        track = d.get("track_drift")
        if track is not None and abs(track) > TRACK_FAST:
            tracked[a["name"]] = int(d["fs"])
        elif abs(scale - 1) >= CLAMPED * max_drift and not (track is not None and abs(track) <= CRYSTAL_DRIFT):
            clamped[a["name"]] = int(d["fs"])
    if not (clamped or tracked):   # (most sessions: the estimator's modules, ~0.3 s of CPU to import, not loaded)
        return {}
    from calib.estimator.clockmodel import impossible_jumps
    from calib.estimator.screen import screen_rows
    from calib.pipeline.setupcheck import arrival_drift

    # a clock that steps (a dropped block) tilts the association and the track too: it is no rate
    jumped = {j["array"] for j in impossible_jumps(feats)}
    los = screen_rows(feats)[0] if set(clamped) - jumped else None
    fast = {name: fs for name, fs in tracked.items() if name not in jumped}
    for name, fs in clamped.items():
        drift = None if name in jumped else arrival_drift(los, name)
        if drift is not None and abs(drift) > 0.5 * FAST_CLOCK:
            fast[name] = fs
    return {name: {"header": fs, "used": fs, "scale": 1.0, "fast_clock": True} for name, fs in fast.items()}


def searched_scale(array, session, threshold=8.0):
    """(scale, support, detection times at the header's rate) of an array's clock against the emission times,
    its chirps detected with the template at each rate of ``SEARCH_SCALES`` × the header's (a matched filter
    finds a sweep only within a few per cent of its own rate); the rate whose detections agree with the most
    emission intervals wins. (1.0, 0.0, []) when none has support."""
    from calib.frontend.consistency import clock_scale
    from calib.frontend.signals import ArrayAudio

    t_emit = session["events"]["t_emit"].to_numpy(float)
    best = (0.0, 1.0, np.zeros(0))
    with ArrayAudio(array) as x:
        for k in SEARCH_SCALES:
            times = _detections(x, session, x.fs * k, threshold)
            s, support = clock_scale(times, t_emit)
            if support > best[0]:   # (times at the rate tried → at the header's: × k)
                best = (support, k * s, times * k)
    support, scale, times = best
    return scale, support, times


def nominal_rate(rate):
    """The rate (Hz) to take a board's samples at, from a measured one: the nearest standard rate when one is
    within ``STANDARD_FIT``, else the measured rate to the hertz."""
    from calib.pipeline.setupcheck import STANDARD_RATES

    near = min(STANDARD_RATES, key=lambda r: abs(r / rate - 1))
    return int(near) if abs(near / rate - 1) < STANDARD_FIT else int(round(rate))


def refine_rates(session, feats, corrections):
    """The corrections with each array's rate refined by the drift a first solve of ``feats`` (extracted at
    the corrected rates) gives it: the chirps' spacing includes the source's range changes (metres over a
    session: up to ~1e-3 of the rate), the solve's drift does not. A fast clock taken at a measured rate that the
    solve still does not trust is dropped. Returns (corrections, changed: an array's rate moved by more than
    ``RATE_REFINE``, or a fast clock dropped). A solve that fails or does not converge changes nothing."""
    from calib.pipeline.retime import first_solve

    sol, _ = first_solve(session, feats, outlier_threshold=OUTLIER_THRESHOLD)
    if sol is None:
        return corrections, False
    drift = dict(zip((str(n) for n in sol["problem"].names), np.asarray(sol["state"].drift, float)))
    unreliable = {str(n) for n in sol["unreliable_arrays"]}
    out, changed = {}, False
    for name, f in corrections.items():
        d = drift.get(name, 0.0)   # (an array the rest contradict is refitted alone: its drift is its own)
        if f.get("fast_clock"):   # a header the chirps' spacing did not contradict: only a clock no crystal gives
            if f["used"] == f["header"] and abs(d) <= FAST_CLOCK:
                continue
            if f["used"] != f["header"] and name in unreliable:
                # read at the measured rate, the array is still not trusted: its drift followed wrong arrivals (a
                # U-shaped room's reflections: -829 ppm for a -85 ppm clock), not its clock; back to its header's
                # rate. (A true fast clock is untrusted only before: its sweep off the template biases its timing.)
                changed = True
                continue
            rate = int(round(f["used"] * (1.0 + d)))
        else:
            rate = nominal_rate(f["used"] * (1.0 + d))
        moved = abs(rate / f["used"] - 1) > RATE_REFINE
        changed |= moved
        out[name] = {**f, "used": rate if moved else f["used"], "refined_by_drift": float(d)}
        if f.get("fast_clock"):   # the measured rate (the samples are taken at it rounded to the hertz)
            out[name]["scale"] = f["used"] * (1.0 + d) / f["header"]
    return out, changed


def detections_only(session, threshold=8.0):
    """The diagnostics :func:`rate_corrections` reads ({"arrays": {name: {"fs", "detections"}}}), from each
    array's chirps detected at its header's rate (``frontend.consistency.detect_chirps``; none matched): for a
    session the frontend refused (an array with too few chirps to associate)."""
    from calib.frontend.signals import ArrayAudio

    out = {}
    for a in session["arrays"]:
        with ArrayAudio(a) as x:
            times = _detections(x, session, x.fs, threshold)
            out[a["name"]] = {"fs": x.fs, "detections": [{"time": float(t)} for t in times]}
    return {"arrays": out}


def _detections(x, session, fs, threshold):
    """Chirp detection times (s at ``fs``) in recording ``x`` read at the rate ``fs``, the template and its band
    built at that rate (``frontend.consistency.detect_chirps``)."""
    from calib.frontend.consistency import detect_chirps
    from calib.frontend.signals import chirp_band, chirp_template

    template = chirp_template(session["chirp"], fs)
    return detect_chirps(x, template, fs, chirp_band(session["chirp"], template, fs),
                         session["events"]["t_emit"].to_numpy(float), threshold)[0]


def with_rates(session, corrections):
    """The session with each corrected array's ``sample_rate`` set to the rate used (a copy)."""
    arrays = [{**a, "sample_rate": corrections[a["name"]]["used"]} if a["name"] in corrections else a
              for a in session["arrays"]]
    return {**session, "arrays": arrays}
