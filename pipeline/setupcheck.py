"""The set-up consistency stage: the mistakes people make in a set-up, found in the data and named.

Run by ``calib check`` (in seconds) and by ``calib run`` before the estimate (docs/reliability.md, "Set-up
mistakes"). Each finding is one line naming the file (and channel) and the fix; a ``failed`` finding means
the calibration cannot be trusted, and ``calib run`` then ends with verdict ``failed`` (exit 3) whatever the
estimate says, its reasons first (``calib.estimator.verdict.with_setup``).

What is checked, and from what:

| mistake | seen as | module |
| --- | --- | --- |
| dead / weak / clipped / duplicated channel | chirp energy, plateaus at the peak level, equal samples | ``frontend.consistency`` |
| inverted polarity | negative inter-mic correlation peaks | ``frontend.consistency`` |
| swapped channels, wrong shape, wrong coordinates | inter-mic delays vs the declared rigid geometry | ``frontend.consistency`` |
| coordinates in cm instead of m, a 3-D board's size | the plane-wave fit's scale ``|w|·c`` (the chirps' consensus) | ``frontend.consistency`` |
| a planar board declared too small | ``|w|·c`` above 1 in many chirps | ``frontend.consistency`` |
| a planar or linear board's size | its DOAs' in-plane (axial) part against the odometry's directions | :func:`geometry_scale_fit` |
| wrong sample rate in a header | the detections' interval ratio to the emission times | ``frontend.consistency`` |
| the same recording for two arrays | equal samples | :func:`identical_recordings` |
| wrong speed of sound / odometry units | ranges from the metric odometry vs the arrivals | :func:`speed_of_sound_fit` |
| which: the declared speed or the odometry's scale | a 3-D board's own c (its mic delays, no odometry) | :func:`sound_cause`, :func:`board_findings` |
| events.csv of another session | arrivals the odometry cannot explain; unmatched chirps | :func:`speed_of_sound_fit` |
| sources on a line or in one non-horizontal plane | the odometry's spread; which arrays' DOAs are 3-D | :func:`trajectory_findings` |
| mirrored geometry, doa_hemisphere on the wrong side, odometry axes mirrored | DOAs that fit the odometry only with an improper rotation | :func:`mirror_findings` |
| speed of sound against the air temperature | session.toml's optional ``temperature`` | :func:`temperature_findings` |

Library use (a notebook)::

    from calib.pipeline.setupcheck import folder_findings, setup_findings
    for f in setup_findings(read_session("rec")): print(f.status, f.text)   # the recordings alone
    for f in folder_findings("rec"): print(f.status, f.text)                # with the features (odometry checks)
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from itertools import combinations
from typing import NamedTuple

import numpy as np

from calib.blas import single_thread_blas
from calib.frontend import consistency as C
from calib.pipeline.headerrate import line_residuals

STATUS_RANK = {"note": 0, "suspect": 1, "failed": 2}
CLOCK_FAIL = 0.005        # an array's clock this far (relative) from the emission clock: a wrong sample rate
CLOCK_SUPPORT = 0.2       # ... found from at least this fraction of the emission intervals
STANDARD_RATES = (8000, 11025, 16000, 22050, 24000, 32000, 44100, 48000, 88200, 96000, 176400, 192000)
SOUND_TOL = 0.03          # relative: a declared speed of sound this far from the odometry's is wrong ...
SOUND_SIGMA = 4.0         # ... and this many standard errors of that estimate ...
SOUND_AGREE = 3.0         # ... the arrays agreeing on it (the spread of their estimates at most this × their errors)
# Closer than SOUND_TOL (±5-10 °C off the declared air's) the poses still bend with it: every array's range from the
# reference scales by c / c0 against the metric odometry (red team, held-out hall 655 at 349 m/s declared 343: five
# arrays 10-21 cm off at 5-19σ, `suspect` naming one). Named, with every non-reference array, beyond SOUND_NEAR_TOL
# when the DOA-aided fit says so at SOUND_NEAR_SIGMA (with the right c0 over 16 rendered sessions: within 0.6 %,
# at most 3.1σ; the arrivals-only fit is not used here: it read one right-c hall −0.3 % at −5.5σ). Not for a source
# moving during the sweep (meta ``doa_time_s``): its arrivals' Doppler shifts bias the fit, +0.4-1.3 % at 2-5σ on
# moving and robot sessions with the right c, +2.8 % at 7σ with a 1 s sweep
BOARD_SIGMA = 3.0         # σ (combined): a 3-D board's own c agrees with the declared one or the odometry's
SOUND_NEAR_TOL = 0.01
SOUND_NEAR_SIGMA = 6.0
ODO_SIGMA_DEFAULT = 0.02  # m: odometry noise per event when meta.json states none
TYPICAL_RANGE_M = 2.0     # m: source distance that turns the odometry's noise into a direction's
SOUND_AT_0C, SOUND_PER_C = 331.3, 0.606  # m/s, m/s per °C: dry air
TEMPERATURE_TOL = 0.015   # relative: humidity and the thermometer allow this much (±5 °C ≈ ±0.9 %)
DOA_TRUST = 2.5           # RMS normalised residual above which the DOAs do not help the speed of sound
VOUCH_DOA_ROWS = 6        # undoubted DOAs fitting the odometry that clear a geometry its pair delays fail (_doa_vouched)
MIRROR_MIN = 4.0          # an array whose quick fit is this many sigmas off (RMS) is also fitted mirrored ...
MIRROR_RATIO = 4.0        # ... and named when the mirror cuts that by this factor (clean: 1.3σ vs 26σ)
S2_FLOOR = 0.25           # the residuals may shrink the stated sigmas by at most 2x in the speed's std
MIN_SOUND_EVENTS = 6      # per array, arrivals needed for a speed-of-sound fit ...
MIN_SOUND_DOF = 4         # ... and arrivals beyond its unknowns (a near-exact fit can be confidently wrong)
SAME_START_M = 1e-3       # m: starts of that fit closer than this lie in one minimum (tried once)
COARSE_ARRIVALS = 400     # a longer chain's starts are first fitted to this many of its arrivals (evenly spread) ...
POLISH_STARTS = 6         # ... and the best this many refined on every arrival
STEP_CHI2 = 36.0          # a break in an array's chain of arrivals must explain this much χ² (a 6σ step) ...
MAX_STEPS = 2             # ... and at most this many breaks are made per array
STEP_CANDIDATES = 8       # breaks refitted per step: the best by the held-position score (_step_scores)
NLOS_MINORITY = 0.5       # an array's arrivals flagged "nlos" left out of the fits while at most this fraction
ODO_RESIDUAL_S = 3e-3     # s: arrivals the odometry cannot explain to better than this (RMS): another session's log
ODO_EXPLAINED = 3.0       # an array whose arrivals and DOAs fit the odometry this well (RMS σ) ties the log to the session
ODO_MISFIT = 12.0         # ... or arrivals and DOAs this many sigmas off (RMS; σ_odo included; real sets: ≤ 5)
MATCHED_FAIL = 0.5        # fewer chirps than this fraction of the events matched: events.csv does not fit
LINE_RATIO = 0.05         # odometry spread: second principal std below this × the first: sources on a line
PLANE_RATIO = 0.05        # third below this × the second: sources in one plane ...
HORIZONTAL_COS = 0.9      # ... which is harmless when horizontal in the reference frame (|n_z| above this)
IDENTICAL_SECONDS = 2.0   # s of audio compared between recordings
# A geometry failed on the strongest chirps (consistency.N_EVENTS) is measured again on up to this many before
# the verdict: at a board beside a reflector the strongest chirps are those the reflection adds to, and their
# delays fit no board (deploy seed 101: a 7-mic circle failed with 1 of its 12 strongest chirps within 2 % of
# the declared geometry; 5 of its 30 fit, the strongest at 14-54 %); a wrong geometry fits none of them either
CONFIRM_EVENTS = 48
GEOMETRY_CHECKS = ("geometry", "geometry scale", "channel geometry", "swapped channels")
PLANAR_SCALE_FAIL = 5.0   # a planar array's scale (an upper bound only) must be off by this much
# the scale fit keeps the DOAs the frontend doubts for a reflection inside the gate (from the surface the array
# is mounted on, a table or a wall, the image is the source mirrored across a plane parallel to the array's:
# the same in-plane direction) ...
# ... and a spread SRP peak (what a mis-scaled geometry itself gives): the robust fit weighs them
SCALE_DOA_DOUBTS = ("doa_reflection", "doa_spread")
SCALE_ROBUST = 3.0        # σ: the scale fit's soft-L1 loss turns linear beyond this ...
SCALE_OUTLIER = 5.0       # ... and drops the DOAs it leaves this far off before its plain (covariance) fit
SOUND_PRIOR = 0.01        # relative: the air's speed of sound near the declared one (±5 °C ≈ ±0.9 %) in that fit
ROTATION_STARTS = 4       # the scale fit refines the best this many of its starting rotations
SATURATED = 0.98          # a DOA's projection this near 1: at the horizon (the measured size clipped there)
SCALE_RANGE = 5.0         # the fitted scale is searched within 1/this .. this (beyond: the delays' own check)
SCALE_TOL = 0.15          # relative: a planar or linear array's declared geometry this much too large or small ...
SCALE_SIGMA = 4.0         # ... and this many standard errors of its fitted scale: the wrong geometry


@dataclass(frozen=True)
class Finding:
    """One set-up finding. status: "failed" (the result cannot be trusted), "suspect" or "note"; what: the
    file it concerns; check: a short name; text: one line naming the file, channel and the fix; array: the
    array's name when one array is concerned."""
    status: str
    what: str
    check: str
    text: str
    array: str | None = None
    arrays: tuple = ()   # the arrays concerned when the finding names several (``array`` then None)
    reading: tuple = ()  # a measured value the estimate's verdict weighs (``board speed``: :func:`board_sound`'s)

    def as_dict(self):
        d = asdict(self)
        if not d["reading"]:
            del d["reading"]
        return d


def worst(findings):
    """The worst status among ``findings`` ("ok" if none)."""
    ranks = [STATUS_RANK[f.status] for f in findings]
    return "ok" if not ranks or max(ranks) == 0 else {1: "suspect", 2: "failed"}[max(ranks)]


def _wav(a):
    return getattr(a["wav"], "name", str(a["wav"]))


# ----------------------------------------------------------------------------------------------- channels
def channel_findings(a, res, c, doas=None):
    """Findings of one array from :func:`calib.frontend.consistency.check_array`'s result ``res``. doas : the
    frontend's DOA of each chirp {detection time: (3,) unit in the array's frame}, or None."""
    d, wav, out = res["delays"], _wav(a), []
    if d is None or not len(d.times):
        return out
    lev = C.channel_levels_db(d)
    dead = [m for m in range(len(lev)) if not lev[m] > C.DEAD_DB]
    for m in dead:
        out.append(Finding("failed", wav, "dead channel", f"{wav} channel {m + 1}: "
                           + ("all zeros" if not np.any(d.energy[:, m]) else f"{lev[m]:.0f} dB below the others")
                           + " in the chirps: a dead or unplugged mic; fix the wiring, or remove the channel and "
                             f"row {m + 1} of the array's mics"))
    for m in range(len(lev)):
        if m not in dead and lev[m] < C.WEAK_DB:
            out.append(Finding("suspect", wav, "weak channel", f"{wav} channel {m + 1}: {lev[m]:.0f} dB below the "
                               "others in the chirps: a loose connector, a covered or damaged mic"))
    for m in np.flatnonzero(d.plateau > C.CLIP_FRACTION):
        out.append(Finding("failed", wav, "clipped", f"{wav} channel {m + 1}: {100 * d.plateau[m]:.1f} % of the "
                           "chirps' samples are clipped (flat at the peak level): lower the input gain or the "
                           "speaker volume and record again"))
    dup = set()
    for m, n in d.identical:
        dup.add(n)
        out.append(Finding("failed", wav, "duplicated channel", f"{wav} channels {m + 1} and {n + 1} hold identical "
                           "samples: one mic recorded twice (a routing or channel-map mistake); fix the channel map"))
    bad = set(dead) | dup
    inv = C.inverted_channels(d, exclude=tuple(bad))
    if inv and 2 * len(inv) >= len(lev) - len(bad):  # no majority to call the right polarity (e.g. a pair)
        names = " and ".join(str(m + 1) for m in inv)
        out.append(Finding("failed", wav, "polarity", f"{wav} channels {names}: opposite polarities (their "
                           "correlation peaks are negative): one side is inverted; rewire it, or multiply it by −1"))
        inv = {}
    for m, frac in inv.items():
        out.append(Finding("failed", wav, "polarity", f"{wav} channel {m + 1}: inverted polarity (its correlation "
                           f"with the other mics is negative in {100 * frac:.0f} % of the pairs): rewire it, or "
                           "multiply the channel by −1"))
    directions = _directions(doas, d.times)
    out += geometry_findings(a, d, c, tuple(sorted(bad)), directions)
    return [replace(f, array=a["name"]) for f in out]


def _geometry_failed(found):
    """True if ``found`` (an array's channel findings) fails its declared mic geometry."""
    return any(f.status == "failed" and f.check in GEOMETRY_CHECKS for f in found)


def _congruent(mics, perm):
    """True if relabelling the mics by ``perm`` preserves every inter-mic distance: a symmetry of the array,
    indistinguishable from a rotated (or mirrored) array in any recording."""
    dist = np.linalg.norm(mics[:, None] - mics[None], axis=-1)
    return bool(np.allclose(dist, dist[np.ix_(perm, perm)], atol=1e-4 * max(dist.max(), 1e-12)))


def geometry_findings(a, d, c, exclude=(), directions=None):
    """The declared geometry against the inter-mic delays: swapped channels, a channel that does not fit,
    the wrong shape, the wrong units. directions: the frontend's DOAs of the delays' events (``C.fit_geometry``)."""
    mics, wav = np.asarray(a["mics"], float), _wav(a)
    g = C.fit_geometry(d, mics, c, exclude, directions)
    if np.isfinite(g.misfit) and g.misfit > C.MISFIT_FLOOR_S and g.ratio > C.MISFIT_NAMED:
        f = _misfit_finding(a, g, mics, C.FIX_RATIO if g.ratio > C.MISFIT_FAIL else C.FIX_NAMED)
        if f is not None:
            return [f]
    if not np.isfinite(g.scale):
        return []
    full3d = C.is_volume(mics[list(g.used)])
    agreed = g.support >= C.CONSENSUS_SUPPORT  # a 3-D array's events, or a planar one's above |w|·c = 1
    fail = (C.SCALE_FAIL_3D if agreed else C.SCALE_FAIL) * np.exp(C.SCALE_SCATTER_K * g.scatter)
    too_big = g.scale > (fail if full3d else PLANAR_SCALE_FAIL)
    # too small only where the events agree: one event above |w|·c = 1 (a reflection) is no evidence (a clean
    # reverberant lab: 1 of 12 at 1.9); a planar array's bound alone can still say too large
    if (too_big and (agreed or not full3d)) or (g.scale < 1 / fail and agreed):
        p10 = 10 ** np.round(np.log10(g.scale))
        hint = (f"in {'cm' if p10 == 100 else 'mm' if p10 == 1000 else 'other units'} instead of m? divide them "
                f"by {p10:g}" if too_big and p10 >= 10 and abs(np.log10(g.scale / p10)) < 0.15
                else f"measure the board: they should be {1 / g.scale:.2g} × the declared ones")
        return [Finding("failed", wav, "geometry scale", f"{wav} (array {a['name']}): the mic coordinates are "
                        f"{g.scale:.3g} × {'larger' if g.scale > 1 else 'smaller'} than the inter-mic delays say "
                        f"(speed of sound {c:g} m/s): {hint}")]
    return []


def _misfit_finding(a, g, mics, fix_ratio):
    """The finding of a geometry that does not fit: the swap or the channel that explains the misfit (cut by
    ``fix_ratio``), else (a misfit above MISFIT_FAIL) the geometry as a whole; None if nothing is named."""
    wav, us = _wav(a), 1e6
    head = f"{wav} (array {a['name']}): the inter-mic delays do not fit the declared mic geometry " \
           f"(misfit {us * g.misfit:.0f} µs, {100 * g.ratio:.0f} % of the largest delay)"
    swaps = {k: v for k, v in g.swaps.items() if not _congruent(mics, _swap_perm(len(mics), *k))}
    if swaps:
        (m, n), v = min(swaps.items(), key=lambda kv: kv[1])
        if v * fix_ratio < g.misfit and v / max(g.span, 1e-12) < C.MISFIT_FAIL:
            return Finding("failed", wav, "swapped channels", f"{head}; with channels {m + 1} and {n + 1} swapped "
                           f"they fit ({us * v:.0f} µs): swap rows {m + 1} and {n + 1} of its mics, or the cables")
    fixes = sorted((v, m) for m, v in g.loo.items() if v * fix_ratio < g.misfit and v / max(g.span, 1e-12)
                   < C.MISFIT_FAIL)
    if len(fixes) == 1 and g.moved[fixes[0][1]][0] * fix_ratio < g.misfit:
        # leaving out any other mic keeps the misfit, and one offset of that mic fits every chirp: misplaced or
        # miswired (a mic that hears a reflection's path in some chirps fits without it, but no offset fits it)
        v, m = fixes[0]
        return Finding("failed", wav, "channel geometry", f"{head}; without channel {m + 1} they fit "
                       f"({us * v:.0f} µs): check row {m + 1} of its mics (a typo?) and that channel's wiring")
    moved = [m for _, m in fixes if g.moved[m][0] * fix_ratio < g.misfit]  # one offset fits every event
    if moved:  # (two rows can explain one typo where the rest leave a direction to just those two mics)
        rows = " or ".join(f"row {m + 1} moved by ({', '.join(f'{100 * x:+.1f}' for x in g.moved[m][1])}) cm"
                           for m in moved)
        return Finding("failed", wav, "channel geometry", f"{head}; with {rows} they fit: check that row of its "
                       "mics (a typo?)")
    if fixes:  # leaving out a mic (or either of two) fits, moving none does: a reflection bends their delays
        names = " or ".join(str(m + 1) for _, m in fixes)
        which = "no offset of that mic does: its delays are" if len(fixes) == 1 else \
            "moving neither does: the delay between these mics is"
        return Finding("note", wav, "pair delay", f"{head}; without channel {names} they fit, {which} off in "
                       "many chirps (a reflection from a surface near the board?); not a set-up mistake")
    if g.ratio <= C.MISFIT_FAIL:
        return None
    if g.best / max(g.span, 1e-12) < C.MISFIT_NAMED:   # several chirps fit it closely: no other board would
        # (its geometry is right, but most chirps reach it by reflections: its arrivals are doubtful, and a
        # reference array's bend every other array: a moving robot's reference in a reverberant lab, 6-17 cm)
        return Finding("suspect", wav, "direct path", f"{head}, but {C.MISFIT_BEST_K} of its chirps fit it within "
                       f"{us * g.best:.0f} µs, which no other board would: most chirps reach it by reflections (a "
                       "wall or an obstacle between it and the speaker?); its arrivals are doubtful")
    return Finding("failed", wav, "geometry", head + WRONG_GEOMETRY)


WRONG_GEOMETRY = (": the mics in session.toml are not this board's (shape, order or coordinates; e.g. a circle "
                  "declared as a line): enter the board's geometry")


def _swap_perm(n, a, b):
    p = np.arange(n)
    p[[a, b]] = p[[b, a]]
    return p


# ----------------------------------------------------------------------------------------------- clocks
def emission_times_scaled(off, n_arrays):
    """Whether the arrays' clock scales ``off`` ({array: scale}, each beyond CLOCK_FAIL) say the emission times
    are scaled, not the headers wrong: every one of ``n_arrays`` (> 1) off, by one scale."""
    return len(off) == n_arrays > 1 and np.ptp(list(off.values())) < CLOCK_FAIL


def _rate_fits_better(times, t_emit, scale):
    """Whether the detections ``times`` follow the emission times more closely at the clock ``scale`` than at the
    nominal rate (median |residual| about each straight line, ``headerrate.line_residuals``): the mode of the
    pairs' interval ratios alone can settle on a chance agreement of misassociated intervals (warehouse seed 102,
    a reverberant 5 dB hall with two reflection-only arrivals left out: 0.9944 at 48 % support for a clock 67 ppm
    fast, whose line at the nominal rate fits every chirp)."""
    times, t_emit = np.sort(np.asarray(times, float)), np.sort(np.asarray(t_emit, float))
    return bool(np.median(np.abs(line_residuals(times, t_emit, scale)[1]))
                < np.median(np.abs(line_residuals(times, t_emit, 1.0)[1])))


def clock_findings(session, results):
    """Each array's clock against the emission times: a rate this far off is a wrong header, not a drift."""
    scales = {a["name"]: results[a["name"]]["clock_scale"] for a in session["arrays"]
              if a["name"] in results and results[a["name"]]["clock_support"] >= CLOCK_SUPPORT}
    t_emit = session["events"]["t_emit"].to_numpy(float)
    off = {k: s for k, s in scales.items() if abs(s - 1) > CLOCK_FAIL
           and _rate_fits_better(results[k]["clock_times"], t_emit, s)}
    if not off:
        return []
    if emission_times_scaled(off, len(session["arrays"])):
        s = float(np.median(list(off.values())))
        return [Finding("failed", "events.csv", "emission clock", f"events.csv: every array's clock runs {s:.4g} × "
                        "the emission times' (t_emit): are they in seconds, from this session?")]
    out = []
    for a in session["arrays"]:
        if a["name"] not in off:
            continue
        s, fs = off[a["name"]], results[a["name"]]["fs"]
        true = fs * s
        near = min(STANDARD_RATES, key=lambda r: abs(r - true))
        guess = f"{near} Hz fits" if abs(near / true - 1) < CLOCK_FAIL else f"the data say ≈ {true:.0f} Hz"
        out.append(Finding("failed", _wav(a), "sample rate", f"{_wav(a)} (array {a['name']}): its clock runs "
                           f"{100 * (s - 1):+.1f} % against the emission times, far beyond a clock drift: the "
                           f"header's sample rate {fs} Hz is wrong ({guess}); declare the board's true rate "
                           f"(sample_rate = N in its [[arrays]] table of session.toml) or rewrite the header",
                           a["name"]))
    return out


# ----------------------------------------------------------------------------------------------- recordings
def identical_recordings(session, seconds=IDENTICAL_SECONDS):
    """Pairs of arrays whose recordings hold the same samples (a copied file): findings."""
    from calib.frontend.signals import ArrayAudio

    clips = {}
    for a in session["arrays"]:
        with ArrayAudio(a) as x:
            n = int(seconds * x.fs)
            mid = max(0, x.frames // 2 - n // 2)
            clips[a["name"]] = (x.fs, np.asarray(x[:, mid : mid + n], np.float64), _wav(a))
    out = []
    for (na, (fa, xa, wa)), (nb, (fb, xb, wb)) in combinations(clips.items(), 2):
        if fa != fb or xa.shape != xb.shape or not np.any(xa):
            continue
        if np.max(np.abs(xa - xb)) <= 1e-4 * np.max(np.abs(xa)):
            out.append(Finding("failed", wb, "identical recordings", f"{wa} and {wb} (arrays {na} and {nb}) hold "
                               "the same samples: one recording copied for two arrays; give each array its own WAV", nb))
    return out


# ----------------------------------------------------------------------------------------------- features
def _flags(column):
    """The frontend's doubts of each row (a ``flag`` column: names joined by '+', empty or NaN for none): sets."""
    return [set(str(f).split("+")) - {""} if isinstance(f, str) else set() for f in column]


def _arrival_chain(tdoa_s, name):
    """(events, relative arrivals, segment id) of one array from its TDOA-S rows chained end to end."""
    rows = tdoa_s[tdoa_s["array"] == name].sort_values("from_event")
    if "flag" in rows:  # the arrivals the frontend found late against the odometry's range track (a blocked
        # direct path): left out while a minority; most of them late: the odometry's own evidence, kept
        late = np.array(["nlos" in f for f in _flags(rows["flag"])], bool)
        if late.mean() <= NLOS_MINORITY:
            rows = rows[~late]
    ev, t, seg = [], [], []
    k = -1
    for f, to, dt in zip(rows["from_event"].to_numpy(int), rows["to_event"].to_numpy(int), rows["tdoa"].to_numpy(float)):
        if not ev or ev[-1] != f:
            k += 1
            ev.append(f), t.append(0.0), seg.append(k)
        ev.append(to), t.append(t[-1] + dt), seg.append(k)
    return np.array(ev, int), np.array(t), np.array(seg, int)


def _kabsch(u, d, w=None, proper=True):
    """Rotation (3, 3) taking the unit vectors ``u`` (K, 3) closest to ``d`` (K, 3); ``proper=False``: the best
    improper one (a rotation times a mirror)."""
    h = (u * (1.0 if w is None else w[:, None])).T @ d
    U, _, Vt = np.linalg.svd(h)
    s = np.sign(np.linalg.det(Vt.T @ U.T)) * (1 if proper else -1)
    return Vt.T @ np.diag([1.0, 1.0, s]) @ U.T


def _one_array_residual(odo, e, y, seg, u, sig_t, sig_d, proper=True):
    """Residual function of one array's quick fit: θ = (x (3), τ per segment, δ, k); arrivals
    ``y = τ_seg + δ·e + k·|odo − x|`` (s, over ``sig_t``) and, where DOAs ``u`` (K, 3, NaN = none) are
    given, ``R u`` against the direction to the odometry's position (the rotation profiled out by
    :func:`_kabsch`, over ``sig_d`` rad)."""
    nseg = seg.max() + 1
    has_u = np.all(np.isfinite(u), axis=1)

    def f(theta):
        x, tau, delta, k = theta[:3], theta[3 : 3 + nseg], theta[3 + nseg], theta[4 + nseg]
        diff = odo - x
        r = np.linalg.norm(diff, axis=1)
        out = [(y - tau[seg] - delta * e - k * r) / sig_t]
        if has_u.sum() >= 3:
            d = diff[has_u] / r[has_u, None]
            R = _kabsch(u[has_u], d, proper=proper)
            out.append(((u[has_u] @ R.T) - d).ravel() / sig_d)
        return np.concatenate(out)
    return f


def _range_projection(odo, e, y, seg):
    """The arrivals' fit ``y ≈ τ_seg + δ·e + k·r``, ``r = |odo − x|``, with τ and δ projected out (variable
    projection), for S candidate positions at once: ``f(X (S, 3)) -> (residuals (S, K), Jacobians (S, K, 3))``,
    exact. ``seg`` (K,) is non-decreasing (segments of the arrival chain). Each call costs a few vectorised
    passes over S × K, not S least-squares solves of (K, nseg + 2)."""
    bounds = np.flatnonzero(np.r_[True, np.diff(seg) != 0])
    cnt = np.diff(np.r_[bounds, len(seg)])[:, None]

    def demean(v):
        """v (S, K, m) less its mean over each segment."""
        return v - np.repeat(np.add.reduceat(v, bounds, axis=1) / cnt, cnt[:, 0], axis=1)

    e_p = demean(e[None, :, None])[0, :, 0]
    ee = float(e_p @ e_p)

    def perp(v):
        """v (S, K, m) projected orthogonally to the segment indicators and to e."""
        v = demean(v)
        return v - e_p[None, :, None] * np.einsum("skm,k->sm", v, e_p)[:, None, :] / ee if ee > 0 else v

    y_p = perp(y[None, :, None])

    def f(X):
        diff = odo[None] - X[:, None, :]                           # (S, K, 3)
        r = np.sqrt(np.einsum("ski,ski->sk", diff, diff))[..., None]
        r_p = perp(r)
        n2 = np.einsum("skm,skm->s", r_p, r_p)[:, None, None]
        safe = np.where(n2 > 0, n2, 1.0)
        k = np.where(n2 > 0, np.einsum("skm,skm->s", r_p, y_p)[:, None, None] / safe, 0.0)
        dr_p = perp(-diff / np.maximum(r, 1e-12))                  # ∂r/∂x projected
        dk = np.einsum("sk,ski->si", (y_p - 2 * k * r_p)[..., 0], dr_p)[:, None, :] / safe
        return (y_p - k * r_p)[..., 0], -r_p * dk - k * dr_p

    return f


def _batch_lm(f, X, max_iter=200, tol=1e-8):
    """Levenberg–Marquardt from several starts at once (each its own damping and stopping): ``f(X (S, n)) ->
    (r (S, K), J (S, K, n))``. Stops a start when a step changes its cost or position by less than ``tol``
    (relative, as MINPACK's ftol / xtol). Returns (X (S, n), cost ½|r|² (S,))."""
    X = np.array(X, float)
    r, J = f(X)
    cost = 0.5 * np.einsum("sk,sk->s", r, r)
    lam = np.full(len(X), 1e-3)
    active = np.ones(len(X), bool)
    eye = np.eye(X.shape[1])
    for _ in range(max_iter):
        a = np.flatnonzero(active)
        Jt = J[a].transpose(0, 2, 1)
        H, g = Jt @ J[a], (Jt @ r[a][..., None])[..., 0]
        D = np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-30)
        M = H + lam[a, None, None] * D[:, :, None] * eye
        try:
            dx = -np.linalg.solve(M, g[..., None])[..., 0]
        except np.linalg.LinAlgError:   # a start whose ranges leave a direction unconstrained: the least-norm step
            dx = -(np.linalg.pinv(M, hermitian=True) @ g[..., None])[..., 0]
        r_n, J_n = f(X[a] + dx)
        c_n = 0.5 * np.einsum("sk,sk->s", r_n, r_n)
        ok = c_n < cost[a]
        done = (np.abs(cost[a] - c_n) <= tol * cost[a]) | \
            (np.linalg.norm(dx, axis=1) <= tol * (np.linalg.norm(X[a], axis=1) + tol))
        acc = a[ok]
        X[acc], r[acc], J[acc], cost[acc] = X[acc] + dx[ok], r_n[ok], J_n[ok], c_n[ok]
        lam[acc] /= 10.0
        lam[a[~ok]] *= 10.0
        active[a[done | (lam[a] > 1e16)]] = False
        if not active.any():
            break
    return X, cost


def _arrival_starts(odo, e, y, seg, n_best=3):
    """Starting positions for :func:`_fit_one_array`: the arrivals alone fitted from starts around the
    trajectory (the linear parameters projected out, :func:`_range_projection`, all starts at once); the
    ``n_best`` best, (x, τ, δ, k) each, less those within ``SAME_START_M`` of a better one (one minimum).

    A chain longer than ``COARSE_ARRIVALS`` is searched coarse to fine: the starts fitted to that many of its
    arrivals (evenly spread: the same trajectory and clock, less noise averaged), then the ``POLISH_STARTS``
    best refined on all of them, a few steps each: the search costs O(K) a few times, not once per start."""
    centre, span = odo.mean(axis=0), max(float(np.ptp(odo, axis=0).max()), 0.5)
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                     [1, 1, 1], [-1, -1, 1], [1, -1, -1], [-1, 1, -1]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    X0 = np.array([centre + r0 * dv for r0 in (1.0 * span, 2.5 * span) for dv in dirs])
    if len(y) > COARSE_ARRIVALS:
        sub = np.unique(np.linspace(0, len(y) - 1, COARSE_ARRIVALS).round().astype(int))
        X, cost = _batch_lm(_range_projection(odo[sub], e[sub], y[sub], np.unique(seg[sub], return_inverse=True)[1]),
                            X0)
        X0 = X[np.argsort(cost, kind="stable")[:POLISH_STARTS]]
    X, cost = _batch_lm(_range_projection(odo, e, y, seg), X0)
    best = _distinct(X[np.argsort(cost, kind="stable")[:n_best]])
    out = []
    for x in best:
        A = np.column_stack([np.eye(seg.max() + 1)[seg], e, np.linalg.norm(odo - x, axis=1)])
        out.append(np.concatenate([x, np.linalg.lstsq(A, y, rcond=None)[0]]))
    return out


def _distinct(X):
    """The positions ``X`` (S, 3), best first, less those within ``SAME_START_M`` of a better one."""
    return X[[i == 0 or np.min(np.linalg.norm(X[:i] - X[i], axis=1)) > SAME_START_M for i in range(len(X))]]


def _fit_one_array(odo, e, y, seg, u, sig_t, sig_d, proper=True, starts=None):
    """One array's position, clock and k = 1 / c from its arrivals (and DOAs) against the metric odometry,
    from ``starts`` (default :func:`_arrival_starts`). Returns (k, std of k, RMS arrival residual s, RMS
    normalised residual)."""
    from scipy.optimize import least_squares

    nseg = seg.max() + 1
    f = _one_array_residual(odo, e, y, seg, u, sig_t, sig_d, proper)
    best = None
    for th in _arrival_starts(odo, e, y, seg) if starts is None else starts:
        sol = least_squares(f, th, x_scale="jac", max_nfev=100)
        if best is None or sol.cost < best.cost:
            best = sol
    J, res = best.jac, best.fun
    n_t = len(y)
    s2 = max(float(res @ res) / max(len(res) - len(best.x), 1), S2_FLOOR)
    cov = np.linalg.pinv(J.T @ J) * s2
    k = float(best.x[4 + nseg])
    return k, float(np.sqrt(max(cov[4 + nseg, 4 + nseg], 0.0))), float(np.sqrt(np.mean((res[:n_t] * sig_t) ** 2))), \
        float(np.sqrt(np.mean(res**2)))


def _doa_rows(features, name, e_id, ambiguous=False, allow=()):
    """(K, 3) DOAs of array ``name`` at events ``e_id`` in its frame (NaN where none, or where the array's DOAs
    are ambiguous: a planar array without hemisphere, a linear one; ``ambiguous=True``: those as given).
    The rows the frontend doubts are left out, but for those whose flags are all in ``allow`` (None: none left out)."""
    meta = features["meta"]
    u = np.full((len(e_id), 3), np.nan)
    if not ambiguous and (name in (meta.get("doa_mirror_normals") or {}) or name in (meta.get("doa_axes") or {})):
        return u
    doa = features["doa"]
    doa = doa[doa["array"] == name]
    if "flag" in doa and allow is not None:  # the frontend's doubts (reflections, occlusion, spread): not the geometry's evidence
        # a boolean array, not a list: an array without DOA rows gives [], which pandas reads as "no columns"
        doa = doa[np.array([f <= set(allow) for f in _flags(doa["flag"])], bool)]
    doa = doa.drop_duplicates("event").set_index("event")
    have = np.isin(e_id, doa.index)
    u[have] = doa.loc[e_id[have], ["ux", "uy", "uz"]].to_numpy(float)
    return u


def _sigmas(meta):
    """(σ of an arrival, σ of a direction) in the quick fits: the odometry's noise is the largest part here,
    ranges and directions to its positions carry it."""
    c0, sig_o = float(meta["speed_of_sound"]), float(meta.get("sigma_odo") or ODO_SIGMA_DEFAULT)
    sig_t = float(np.hypot(float(meta.get("sigma_tdoa") or 1e-5) / np.sqrt(2), sig_o / c0))
    sig_d = float(np.hypot(np.radians(float(meta.get("sigma_doa_deg") or 1.0)), sig_o / TYPICAL_RANGE_M))
    return sig_t, sig_d


def _array_data(features, name):
    """One array's arrivals against the odometry: (odometry (K, 3), emission times from the first (K,),
    arrivals less the emission intervals (K,), segment ids (K,), event ids (K,)); None when too few."""
    ev = features["events"].set_index("event")
    e_id, t, seg = _arrival_chain(features["tdoa_s"], name)
    keep = np.isin(e_id, ev.index)
    if keep.sum() < MIN_SOUND_EVENTS:
        return None
    e_id, t, seg = e_id[keep], t[keep], np.unique(seg[keep], return_inverse=True)[1]
    te = ev.loc[e_id, "t_emit"].to_numpy(float)
    odo = ev.loc[e_id, ["odom_x", "odom_y", "odom_z"]].to_numpy(float) + _motion_shift(features, e_id)
    return odo, te - te[0], t - (te - te[0]), seg, e_id


def _motion_shift(features, e_id):
    """(K, 3) m: where the source of a sweep moving with velocity v (events.csv ``vel_*``) seems to be to the
    arrivals: a matched filter shifts an arrival by β (v·u)/c (estimator/motion.py; β meta ``chirp_drift_bias``),
    to first order the range of the source moved by β v. Zero without velocities: a robot stopped to chirp
    (a −5 % speed of sound was read from a robot driving steadily away from most arrays before)."""
    from calib.tables import event_velocities

    events = features["events"]
    v = event_velocities(events)
    beta = float(features["meta"].get("chirp_drift_bias") or 0.0)
    if v is None or not beta:
        return np.zeros((len(e_id), 3))
    row = {int(e): k for k, e in enumerate(events["event"].to_numpy())}
    return beta * v[[row[int(e)] for e in e_id]]


def split_steps(odo, e, y, seg, sig_t, max_steps=MAX_STEPS):
    """Segment ids ``seg`` with the chain of arrivals broken where it steps: an emission interval logged wrong
    (every array then sees the same error on that TDOA-S row: 0.7–0.9 ms in two of the real sets) or a block
    of samples dropped or inserted (one array). A step shifts every later arrival of its segment, which no
    range explains; each break frees an offset, so one is made only where it cuts the arrivals' χ² by
    STEP_CHI2 (the array's position refitted), at most ``max_steps``. The breaks tried are the STEP_CANDIDATES
    the fit at the current segments and position points to (:func:`_step_scores`, every arrival at once): a
    step also pulls the position of a short chain, so the best score alone can miss it."""
    from scipy.optimize import least_squares

    seg = np.asarray(seg, int).copy()

    def start(sg):  # the best start of a segmentation (a large step sends the unbroken chain's position far)
        return _arrival_starts(odo, e, y, sg, n_best=1)[0][:3]

    def fit(sg, x0):  # (χ², position): the linear parameters projected out, the position refined from x0
        def res(x):
            A = np.column_stack([np.eye(sg.max() + 1)[sg], e, np.linalg.norm(odo - x, axis=1)])
            return (y - A @ np.linalg.lstsq(A, y, rcond=None)[0]) / sig_t
        sol = least_squares(res, x0, method="lm", max_nfev=50)
        return 2 * sol.cost, sol.x

    base, x = fit(seg, start(seg))
    for _ in range(max_steps):
        score = _step_scores(odo, e, y, seg, x)
        cands = [j for j in np.argsort(-score, kind="stable")[:STEP_CANDIDATES] if score[j] > 0]
        trials = [np.where((np.arange(len(y)) >= j) & (seg == seg[j]), seg + 1, seg + (seg > seg[j])) for j in cands]
        if not trials:
            break
        x0 = start(trials[0])  # the candidates differ by a few arrivals: one start serves them all
        (chi2, x_trial), trial = min(((fit(t, x0), t) for t in trials), key=lambda ft: ft[0][0])
        if base - chi2 < STEP_CHI2:
            break
        seg, base, x = trial, chi2, x_trial
    return seg


def _step_scores(odo, e, y, seg, x):
    """For every arrival j, how much a step before it (an offset added to the arrivals from j to the end of
    its segment ``seg``, contiguous) would reduce the residual sum of squares of the linear fit (an offset per
    segment, δ, 1/c) with the position ``x`` held: (hᵀr)² / (hᵀh − |Qᵀh|²), ``r`` the residuals, ``Q`` an
    orthonormal basis of the fit's columns and ``h`` the step's indicator, all ``h`` at once by cumulative sums
    from the end. 0 where no step can be placed (a segment's first arrival) or it is not identifiable."""
    A = np.column_stack([np.eye(seg.max() + 1)[seg], e, np.linalg.norm(odo - x, axis=1)])
    Q = np.linalg.qr(A)[0]
    r = y - Q @ (Q.T @ y)
    tail = np.empty((len(y), 1 + Q.shape[1] + 1))
    for s_id in np.unique(seg):  # sums over i >= j within j's segment
        idx = np.flatnonzero(seg == s_id)
        v = np.column_stack([np.ones(len(idx)), Q[idx], r[idx]])
        tail[idx] = np.cumsum(v[::-1], axis=0)[::-1]
    hh, qh, hr = tail[:, 0], tail[:, 1:-1], tail[:, -1]
    den = hh - np.sum(qh**2, axis=1)
    first = np.r_[True, seg[1:] != seg[:-1]]
    ok = ~first & (den > 1e-9 * np.maximum(hh, 1.0))
    return np.where(ok, hr**2 / np.where(ok, den, 1.0), 0.0)


class ArrivalChain(NamedTuple):
    """One array's arrivals against the odometry (:func:`_array_data`), its chain broken where it steps
    (:func:`split_steps`) and the starts of its fits (:func:`_arrival_starts`): what the fits with a proper and
    a mirrored rotation share (the arrivals alone decide it)."""
    odo: np.ndarray
    e: np.ndarray
    y: np.ndarray
    seg: np.ndarray
    e_id: np.ndarray
    starts: list


def arrival_chain(features, name, sig_t):
    """Array ``name``'s :class:`ArrivalChain` (None: too few arrivals for the speed of sound's fit)."""
    data = _array_data(features, name)
    if data is None:
        return None
    odo, e, y, seg, e_id = data
    seg = split_steps(odo, e, y, seg, sig_t)
    if len(y) - (seg.max() + 1) - 5 < MIN_SOUND_DOF:  # x (3), δ, k and an offset per segment
        return None
    return ArrivalChain(odo, e, y, seg, e_id, _arrival_starts(odo, e, y, seg))


def arrival_drift(features, name):
    """Array ``name``'s clock drift against the emission times from its arrivals alone (TDOA-S chained against the
    odometry's ranges from its best-fitting position, c free: :func:`arrival_chain`'s best start), or None when
    too few arrivals. A quick look (no DOAs, no other array): ~1e-6 over a minute of chirps."""
    chain = arrival_chain(features, name, _sigmas(features["meta"])[0])
    return None if chain is None or not chain.starts else float(chain.starts[0][-2])


def speed_of_sound_fit(features, proper=True, arrays=None, chains=None, doas=True):
    """Speed of sound from the metric odometry: per array, its arrivals (TDOA-S chained, less the emission
    times) against the ranges from an unknown position to the odometry's source positions, its DOAs against
    the directions to them (the angles between sources fix the metric distance, whatever c). Returns
    {array: (c, std of c, RMS arrival residual s, RMS normalised residual)} for the arrays with enough
    arrivals; c is inf (std inf) where the best fit has no positive 1/c (no range explains the arrivals).
    proper=False: each array's DOAs are fitted with a mirror (an improper rotation) instead; arrays: only these.
    chains: {array: :class:`ArrivalChain` or None} already built (reused, the missing ones added). doas=False:
    the arrivals alone, which owe nothing to the declared speed c0: the frontend measures a planar (linear)
    array's DOA as c0 × its slowness in the plane (on the axis), so a wrong c0 bends those DOAs toward a geometry
    that fits c0 and scatters them across the band (lab3 declared at 400 m/s: the session's DOA σ 1.4°, at 343
    m/s 0.24°); the DOA-aided fit, its residuals normalised by that σ, then keeps them and leans toward c0."""
    meta = features["meta"]
    sig_t, sig_d = _sigmas(meta)
    chains = {} if chains is None else chains
    out = {}
    with single_thread_blas():  # small matrices (calib.blas)
        for name in meta["arrays"] if arrays is None else arrays:
            if name not in chains:
                chains[name] = arrival_chain(features, name, sig_t)
            fit = _array_sound_fit(features, name, chains[name], sig_t, sig_d, proper, doas)
            if fit is not None:
                out[name] = fit
    return out


def _array_sound_fit(features, name, chain, sig_t, sig_d, proper, doas=True):
    """One array's entry of :func:`speed_of_sound_fit` from its :class:`ArrivalChain` (None: too few arrivals)."""
    if chain is None:
        return None
    odo, e, y, seg, e_id, starts = chain
    u = _doa_rows(features, name, e_id) if doas else np.full((len(y), 3), np.nan)
    k, sk, rms, misfit = _fit_one_array(odo, e, y, seg, u, sig_t, sig_d, proper, starts)
    if misfit > DOA_TRUST and np.any(np.isfinite(u)):
        # DOAs that do not fit (a wrong speed of sound also bends a planar array's elevations): c from
        # the arrivals alone; the misfit kept for the mirror and the odometry tests
        k, sk, rms, _ = _fit_one_array(odo, e, y, seg, np.full_like(u, np.nan), sig_t, sig_d, starts=starts)
    return (1.0 / k, sk / k**2, rms, misfit) if k > 0 else (np.inf, np.inf, rms, misfit)


def _usable(fits):
    """The speed-of-sound fits {array: (c, std, ...)} with a finite, positive std."""
    return {k: v for k, v in fits.items() if np.isfinite(v[1]) and v[1] > 0}


def _sound_mean(fits):
    """(c, std, Birge ratio) of the arrays' speeds of sound {array: (c, std, ...)}, weighted by their errors.
    Arrays that disagree beyond their errors (a reflection-only array, a fit with few arrivals): the spread, not
    the stated errors, is then the mean's uncertainty (the Birge ratio)."""
    w = np.array([1 / v[1] ** 2 for v in fits.values()])
    cs = np.array([v[0] for v in fits.values()])
    c_hat = float(np.sum(w * cs) / np.sum(w))
    birge = np.sqrt(max(float(np.sum(w * (cs - c_hat) ** 2)) / max(len(cs) - 1, 1), 1.0))
    return c_hat, float(birge / np.sqrt(np.sum(w))), float(birge)


# ----------------------------------------------------------------------------------------------- geometry scale
def _subspace(mics):
    """(3, r) orthonormal basis of what the array's delays measure of a direction: its axis (r = 1, a linear
    array), its plane (r = 2); None for a volume array (its delays measure the scale directly) or one mic."""
    from calib.frontend.doa import mic_geometry

    kind, v = mic_geometry(mics)
    if kind == "linear":
        return np.asarray(v, float)[:, None]
    if kind == "planar":
        return np.linalg.svd(np.asarray(v, float)[None, :])[2][1:].T
    return None


def _projected(h):
    """A direction's measured projection ``h`` (K, r) as the array's SRP reports it: clipped to the unit ball
    (a geometry declared too small asks for more than a plane wave gives: the search stops at the horizon)."""
    n = np.linalg.norm(h, axis=1, keepdims=True)
    return h / np.maximum(n, 1.0)


def _scale_residual(odo, e, y, seg, m, B, sig_t, sig_d, c0):
    """Residual of the scaled-geometry fit: θ = (x, τ per segment, δ, k, rotation vector (3), log s); the
    arrivals as :func:`_one_array_residual`, and the DOAs' projections ``m`` (K, r) on the array's subspace
    ``B`` (3, r) against ``Bᵀ Rᵀ d / s`` (``d`` the directions to the odometry's positions): what the array
    measures when its declared geometry is ``s`` × the true one; the speed of sound held near the declared
    ``c0`` (SOUND_PRIOR: checked on its own before, :func:`sound_findings`)."""
    from scipy.spatial.transform import Rotation

    nseg = seg.max() + 1
    arrivals = _one_array_residual(odo, e, y, seg, np.full((len(odo), 3), np.nan), sig_t, sig_d)
    has = np.all(np.isfinite(m), axis=1)

    def f(theta):
        x, rv, log_s = theta[:3], theta[5 + nseg : 8 + nseg], theta[8 + nseg]
        diff = odo[has] - x
        d = diff / np.linalg.norm(diff, axis=1, keepdims=True)
        h = _projected(d @ Rotation.from_rotvec(rv).as_matrix() @ B / np.exp(log_s))
        return np.concatenate([arrivals(theta[: 5 + nseg]), ((m[has] - h) / sig_d).ravel(),
                               [(theta[4 + nseg] * c0 - 1) / SOUND_PRIOR]])
    return f


def _rotation_starts(u, d, B):
    """Starting rotations (rotation vectors) of the scaled fit: the DOAs as given and mirrored across the
    array's plane (a planar array without hemisphere), taken to the directions ``d`` by :func:`_kabsch`,
    and the 24 rotations of the cube (a linear array's DOAs fix its axis only)."""
    from scipy.spatial.transform import Rotation

    has = np.all(np.isfinite(u), axis=1)
    starts = []
    if has.sum() >= 3:
        flips = [np.eye(3)] + ([np.eye(3) - 2 * np.outer(n, n) for n in [np.cross(*B.T)]] if B.shape[1] == 2 else [])
        starts = [Rotation.from_matrix(_kabsch(u[has] @ F.T, d[has])).as_rotvec() for F in flips]
    return starts + list(Rotation.create_group("O").as_rotvec())


def geometry_scale_fit(features, name, mics):
    """The factor ``s`` by which array ``name``'s declared geometry ``mics`` is larger than the one its DOAs
    and arrivals fit against the metric odometry: (s, std of log s, RMS normalised residual at s, at s = 1);
    None for a volume array (the delays measure its scale, :func:`calib.frontend.consistency.fit_geometry`)
    or too few data. A planar (linear) array's delays measure only the in-plane part (the axial component)
    of a source's direction, its size times that part: a geometry ``s`` × too large shrinks it by ``s`` (the
    frontend reports the sources higher above the plane, or nearer the axis's normal), which the delays alone
    cannot tell from a source that is; the odometry's positions seen from the array can."""
    from scipy.optimize import least_squares

    B = _subspace(np.asarray(mics, float))
    data = _array_data(features, name)
    if B is None or data is None:
        return None
    odo, e, y, seg, e_id = data
    u = _doa_rows(features, name, e_id, ambiguous=True, allow=SCALE_DOA_DOUBTS)
    has = np.all(np.isfinite(u), axis=1)
    if has.sum() < MIN_SOUND_EVENTS:
        return None
    sig_t, sig_d = _sigmas(features["meta"])
    c0 = float(features["meta"]["speed_of_sound"])
    arr = _one_array_residual(odo, e, y, seg, np.full_like(u, np.nan), sig_t, sig_d)
    theta0 = min((least_squares(arr, th, x_scale="jac", max_nfev=100) for th in _arrival_starts(odo, e, y, seg)),
                 key=lambda sol: sol.cost).x
    diff = odo - theta0[:3]
    d = diff / np.linalg.norm(diff, axis=1, keepdims=True)
    m = u @ B
    f = _scale_residual(odo, e, y, seg, m, B, sig_t, sig_d, c0)
    # the arrivals' parameters held: a cheap first pass over the starting rotations
    starts = sorted(_rotation_starts(u, d, B), key=lambda rv: float(np.sum(f(np.r_[theta0, rv, 0.0]) ** 2)))
    best = min((least_squares(lambda q: f(np.r_[theta0, q[:3], np.clip(q[3], -1.0, 1.0)]), np.r_[rv, 0.0], max_nfev=60)
                for rv in starts[:ROTATION_STARTS]), key=lambda sol: sol.cost)
    lo, hi = np.full(len(best.x) + len(theta0), -np.inf), np.full(len(best.x) + len(theta0), np.inf)
    lo[-1], hi[-1] = -np.log(SCALE_RANGE), np.log(SCALE_RANGE)
    start = np.r_[theta0, best.x[:-1], np.clip(best.x[-1], 0.9 * lo[-1], 0.9 * hi[-1])]
    sol = least_squares(f, start, x_scale="jac", loss="soft_l1", f_scale=SCALE_ROBUST, bounds=(lo, hi), max_nfev=200)
    # the DOAs the robust fit leaves out (a reflection, a spread peak) dropped; the plain fit's covariance then
    res = np.linalg.norm(sol.fun[len(y):len(y) + B.shape[1] * has.sum()].reshape(-1, B.shape[1]), axis=1)
    m[np.flatnonzero(has)[res > SCALE_OUTLIER]] = np.nan
    if np.all(np.isfinite(m), axis=1).sum() < MIN_SOUND_EVENTS:
        return None
    f = _scale_residual(odo, e, y, seg, m, B, sig_t, sig_d, c0)
    fixed = least_squares(lambda q: f(np.r_[q, 0.0]), sol.x[:-1], x_scale="jac", max_nfev=200)
    sol = min((least_squares(f, x0, x_scale="jac", bounds=(lo, hi), max_nfev=200)
               for x0 in (sol.x, np.r_[fixed.x, 0.0])), key=lambda r: r.cost)
    used = np.linalg.norm(m[np.all(np.isfinite(m), axis=1)], axis=1)
    if abs(sol.x[-1]) > 0.99 * hi[-1] or not np.any(sol.jac[:, -1]) or \
            (sol.x[-1] < 0 and np.mean(used > SATURATED) >= 0.5):
        # most sources at the array's horizon (or beyond, for the declared size): the DOAs bound the size from
        # one side only; the delays tell a geometry too small (calib.frontend.consistency.fit_geometry)
        return None
    s2 = max(float(sol.fun @ sol.fun) / max(len(sol.fun) - len(sol.x), 1), S2_FLOOR)
    cov = np.linalg.pinv(sol.jac.T @ sol.jac) * s2
    return (float(np.exp(sol.x[-1])), float(np.sqrt(max(cov[-1, -1], 0.0))), float(np.sqrt(np.mean(sol.fun**2))),
            float(np.sqrt(np.mean(fixed.fun**2))))


def scale_findings(features, source="session.toml", arrays=None):
    """Planar and linear arrays whose declared geometry is too large or too small for their DOAs against the
    odometry (:func:`geometry_scale_fit`; the mics from meta ``mics``; arrays: only these)."""
    mics, out = features["meta"].get("mics") or {}, []
    with single_thread_blas():  # small matrices (calib.blas)
        fits = {name: geometry_scale_fit(features, name, mics[name])
                for name in (features["meta"]["arrays"] if arrays is None else arrays) if name in mics}
    for name, fit in fits.items():
        if fit is None:
            continue
        s, sd, rms, rms1 = fit
        if rms > DOA_TRUST or abs(np.log(s)) < max(np.log1p(SCALE_TOL), SCALE_SIGMA * sd):
            continue
        kind = "linear" if _subspace(np.asarray(mics[name], float)).shape[1] == 1 else "planar"
        seen = "angles to its axis" if kind == "linear" else "in-plane directions"
        out.append(Finding("failed", source, "geometry scale", f"{source}: array {name}'s mic coordinates are "
                           f"{s:.2f} × {'larger' if s > 1 else 'smaller'} than the geometry its DOAs fit against the "
                           f"odometry ({seen} off by {rms1:.1f}σ RMS as declared, {rms:.1f}σ at {s:.2f}; ± "
                           f"{100 * sd:.0f} %): the wrong board, or a radius typed as a diameter (or the reverse)? "
                           f"measure its mics: they should be about {1 / s:.2f} × the declared ones", name))
    return out


def sound_findings(features, fits=None, source="session.toml", board=None, chains=None):
    """The declared speed of sound against the odometry's metric scale, and arrivals the odometry cannot
    explain (events.csv of another session). source: the file that declares the speed of sound (a features
    folder's meta.json for ``calib estimate``). board: the 3-D boards' own speed of sound (:func:`board_sound`)
    or None: where it tells which is wrong, the declared speed or the odometry's scale (:func:`sound_cause`), the
    finding names that one alone. fits, chains: :func:`speed_of_sound_fit`'s, if already made."""
    chains = {} if chains is None else chains  # each array's arrivals, split and started once for every fit
    fits = speed_of_sound_fit(features, chains=chains) if fits is None else fits
    c0 = float(features["meta"]["speed_of_sound"])
    out = mirror_findings(features, fits, chains)
    if out:
        return out
    bad = {k: v for k, v in fits.items() if v[2] > ODO_RESIDUAL_S or v[3] > ODO_MISFIT or not np.isfinite(v[0])}
    # another session's log leaves no array explained; one array that fits it to its noise says the log is this
    # session's, and the others' misfits have causes of their own (an L-shaped room's reflection-only arrivals)
    explained = any(v[3] <= ODO_EXPLAINED and np.isfinite(v[0]) for v in fits.values())
    if bad and not explained and len(bad) >= max(1, len(features["meta"]["arrays"]) // 2 + 1):  # most arrays
        worst_ = max(v[3] for v in bad.values())
        return [Finding("failed", "events.csv", "odometry vs arrivals", f"events.csv: the odometry does not explain "
                        f"the chirps' arrival times and directions (residuals up to {worst_:.0f}× their sigma in "
                        f"{', '.join(sorted(bad))}): is events.csv from this session (times and odometry)?")]
    good = _usable({k: v for k, v in fits.items() if k not in bad})
    if not good:
        return out
    # a wrong declared speed of sound is common to every array: arrays that disagree this much show another cause.
    # Tested on the DOA-aided fits (the more precise when c0 is right) and on the arrivals alone (their power owes
    # nothing to the DOAs' σ, which a wrong c0 inflates while it bends the DOAs toward itself: doas=False)
    arrivals = speed_of_sound_fit(features, arrays=list(good), chains=chains, doas=False)
    tests = [_sound_mean(f) for f in (good, _usable(arrivals)) if f]
    wrong = [(c_hat, sd) for c_hat, sd, birge in tests
             if abs(c_hat / c0 - 1) > SOUND_TOL and abs(c_hat - c0) > SOUND_SIGMA * sd and birge <= SOUND_AGREE]
    if wrong:
        c_hat, sd = max(wrong, key=lambda t: abs(t[0] - c0) / t[1])
        rel = c_hat / c0 - 1
        cause = sound_cause(c_hat, sd, c0, board)
        if cause is not None:
            return out + [_blamed(cause, "failed", c_hat, sd, c0, board, source)]
        p10 = 10 ** np.round(np.log10(c_hat / c0))
        # the ranges fix only c / (the odometry's scale): a wheel-diameter or encoder error reads the same
        units = (f" — or the odometry is not in metres ({p10:g} × fits)" if p10 != 1 and
                 abs(np.log10(c_hat / c0 / p10)) < 0.1 else
                 f" — or, if the declared speed of sound is right, the odometry's distances are {abs(100 * rel):.0f} % "
                 f"too {'long' if rel > 0 else 'short'} (wheel diameter, encoder scale): then correct events.csv, "
                 "not the speed of sound")
        out.append(Finding("failed", source, "speed of sound", f"{source}: speed_of_sound = {c0:g} m/s, "
                           f"but the metric odometry says {c_hat:.0f} ± {sd:.0f} m/s ({100 * rel:+.0f} %): set it "
                           f"to the air's (343 m/s at 20 °C; 331.3 + 0.606·T °C){units}"))
    if not wrong:
        out += _near_sound(features, *tests[0], c0, source, board)   # (tests[0]: the DOA-aided fit of ``good``)
    if not out:  # the speed of sound fits the odometry: each planar or linear array's size against it
        # (the arrays whose arrivals fit: a wrong size raises the DOAs' misfit, not the arrivals')
        # (arrays too short for a speed of sound of their own are tried: their DOAs place them)
        out += scale_findings(features, source, arrays=[k for k in features["meta"]["arrays"] if k not in fits
                                                        or (fits[k][2] <= ODO_RESIDUAL_S and np.isfinite(fits[k][0]))])
    return out


def _non_reference(features):
    """The names of every array but the reference (those a wrong speed of sound moves)."""
    ref = features["meta"].get("reference_array")
    return tuple(str(a) for a in features["meta"]["arrays"] if str(a) != str(ref))


def _blamed(cause, status, c_hat, sd, c0, board, source, arrays=()):
    """The speed-of-sound finding when the boards' own delays (:func:`sound_cause`) name the culprit: the declared
    speed ("sound": `--speed-of-sound auto` then places the arrays at the odometry's metre, which the boards
    vouch for) or the odometry's scale ("odometry": c stays declared, as by default; auto would scale every array
    by the odometry's error)."""
    rel = c_hat / c0 - 1
    said = (f"the arrivals against the odometry say {c_hat:.1f} ± {sd:.1f} m/s ({100 * rel:+.1f} %) and "
            f"{_board_text(board)}")
    if cause == "sound":
        return Finding(status, source, "speed of sound", f"{source}: speed_of_sound = {c0:g} m/s is off: {said}, "
                       f"within their errors, so the odometry's scale is right: set it to about {board[0]:.0f} m/s "
                       "(the air's at the session's temperature, 331.3 + 0.606·T °C), or solve it "
                       "(`--speed-of-sound auto`: the boards confirm the odometry's metre it relies on)",
                       arrays=arrays)
    return Finding(status, "events.csv", "odometry scale", f"events.csv: the odometry's distances are "
                   f"{abs(100 * rel):.1f} % too {'long' if rel > 0 else 'short'} (wheel diameter, encoder scale), "
                   f"not the speed of sound: {said}, the declared {c0:g} m/s within their errors; correct the "
                   "odometry (its positions × " f"{c0 / c_hat:.4f}) and keep the declared speed fixed (the "
                   "default; `--speed-of-sound auto` would scale every array by the odometry's error)", arrays=arrays)


def _near_sound(features, c_hat, sd, birge, c0, source, board=None):
    """A declared speed of sound between SOUND_NEAR_TOL and SOUND_TOL off the DOA-aided fit ``c_hat`` ± ``sd``
    (:func:`_sound_mean`), at SOUND_NEAR_SIGMA and the arrays agreeing, the source static during its sweeps: a
    `suspect` finding naming every non-reference array (their ranges from the reference scale with c / c0). []
    otherwise."""
    rel = c_hat / c0 - 1
    if (features["meta"].get("doa_time_s") or abs(rel) <= SOUND_NEAR_TOL or abs(c_hat - c0) <= SOUND_NEAR_SIGMA * sd
            or birge > SOUND_AGREE):
        return []
    names = _non_reference(features)
    cause = sound_cause(c_hat, sd, c0, board)
    if cause is not None:
        return [_blamed(cause, "suspect", c_hat, sd, c0, board, source, names)]
    text = (f"{source}: speed_of_sound = {c0:g} m/s, but the arrivals and DOAs against the metric odometry say "
            f"{c_hat:.1f} ± {sd:.1f} m/s ({100 * rel:+.1f} %, {abs(c_hat - c0) / sd:.0f}σ): every array's distance "
            f"from the reference is scaled by it (about {abs(100 * rel):.1f} cm per metre; named: "
            f"{', '.join(names)}); set it to the air's at the session's temperature (331.3 + 0.606·T °C) — or, if "
            f"it is right, the odometry's distances are {abs(100 * rel):.1f} % too {'long' if rel > 0 else 'short'}")
    return [Finding("suspect", source, "speed of sound", text, arrays=names)]


def mirror_findings(features, fits, chains=None):
    """Arrays whose DOAs fit the odometry only as a mirror image (an improper rotation): their mic geometry
    is mirrored or their doa_hemisphere is on the wrong side; all of them: the odometry's axes are mirrored
    (x and y swapped, or one negated). Observable only where the sources span 3-D: with a planar path the
    array's mirror image across it fits as well (docs/reliability.md). chains: as :func:`speed_of_sound_fit`'s."""
    poor = [k for k, v in fits.items() if v[3] > MIRROR_MIN]
    if not poor:
        return []
    mirrored = speed_of_sound_fit(features, proper=False, arrays=poor, chains=chains)
    named = [k for k in poor if k in mirrored and mirrored[k][3] * MIRROR_RATIO < fits[k][3]]
    if not named:
        return []
    if len(named) == len(fits) > 1:
        return [Finding("failed", "events.csv", "odometry axes", "events.csv: every array's DOAs fit the odometry "
                        "only mirrored (residuals " + ", ".join(f"{fits[k][3]:.0f}→{mirrored[k][3]:.1f}σ" for k in named)
                        + "): the odometry's axes are mirrored against the reference array's (x and y swapped, or "
                        "one axis negated; fix odom_x, odom_y, odom_z), or every DOA points away from its source "
                        "(doa.csv's convention: toward it)")]
    return [Finding("failed", "session.toml", "mirrored geometry", f"session.toml: array {k}'s DOAs fit the "
                    f"directions to the odometry's positions only mirrored (residuals {fits[k][3]:.0f}σ → "
                    f"{mirrored[k][3]:.1f}σ): its mics are mirrored (y typed as −y, or its channels in reversed order) "
                    "or its doa_hemisphere is on the wrong side (or its DOAs point away from the source); fix its "
                    "mics or doa_hemisphere", k) for k in named]


def temperature_findings(session):
    """session.toml's speed of sound against its (optional) air temperature: c = 331.3 + 0.606·T m/s."""
    if session.get("temperature") is None:
        return []
    t, c0 = float(session["temperature"]), float(session["speed_of_sound"])
    c_t = SOUND_AT_0C + SOUND_PER_C * t
    if abs(c0 / c_t - 1) <= TEMPERATURE_TOL:
        return []
    return [Finding("failed", "session.toml", "speed of sound", f"session.toml: speed_of_sound = {c0:g} m/s, but "
                    f"its temperature {t:g} °C gives {c_t:.1f} m/s in air ({100 * (c0 / c_t - 1):+.1f} %): correct "
                    "one of them")]


def trajectory_findings(events, features=None):
    """Sources on a line, or in one plane that is not horizontal in the reference frame: the arrays' mirror
    images across it (rotations about the line) explain the TDOAs as well. Across a plane only an array whose
    DOAs do not fix a 3-D direction (:func:`mirror_ambiguous`) can be mirrored (a 3-D one would need an
    improper rotation): with ``features`` known, those arrays are named (``suspect``; ``failed`` when every
    non-reference array is one) and the others are calibrated (lab3 in a vertical plane: 0.2-0.3 cm)."""
    odo = events[["odom_x", "odom_y", "odom_z"]].to_numpy(float)
    if len(odo) < 3:
        return []
    _, s, vt = np.linalg.svd(odo - odo.mean(axis=0), full_matrices=False)
    s = s / np.sqrt(len(odo))
    if s[0] <= 0:
        return [Finding("failed", "events.csv", "trajectory", "events.csv: the odometry never moves: the sources' "
                        "positions cannot place the arrays; drive the robot around the room")]
    if s[1] < LINE_RATIO * s[0]:
        return [Finding("failed", "events.csv", "trajectory", f"events.csv: the sources lie on a line (spread "
                        f"{s[0]:.2f} m along it, {s[1]:.3f} m across): each array may turn about it freely; drive "
                        "a path that turns")]
    n = vt[2]
    if not (s[2] < PLANE_RATIO * s[1] and abs(n[2]) < HORIZONTAL_COS):
        return []
    text = f"events.csv: the sources lie in one plane that is not horizontal (normal {n[0]:+.2f}, {n[1]:+.2f}, " \
           f"{n[2]:+.2f}): "
    if features is None:
        return [Finding("failed", "events.csv", "trajectory", text + "every array's mirror image across it fits "
                        "the delays as well; drive a path that leaves it")]
    loose, others = mirror_ambiguous(features)
    if loose and loose == others:
        return [Finding("failed", "events.csv", "trajectory", text + "no array's DOAs fix a 3-D direction, so each "
                        "one's mirror image across it fits the delays and DOAs as well; drive a path that leaves it")]
    return [Finding("suspect", "events.csv", "trajectory", text + f"array {name}'s DOAs do not fix a 3-D direction "
                    "(a planar board without doa_hemisphere, a linear board or a pair), so its mirror image across "
                    "the plane fits as well: its pose may be mirrored; state its doa_hemisphere, or drive a path "
                    "that leaves the plane", name) for name in loose]


def mirror_ambiguous(features):
    """(names, others): the non-reference arrays of ``features`` whose DOAs do not fix a 3-D direction (meta
    ``doa_mirror_normals``: planar without a hemisphere; ``doa_axes``: linear boards and pairs; or no DOA rows),
    and all non-reference arrays, both in the features' order."""
    meta = features["meta"]
    ref = meta.get("reference_array")
    others = [str(a) for a in meta["arrays"] if str(a) != str(ref)]
    with_doa = set(features["doa"]["array"].astype(str)) if features.get("doa") is not None else set()
    loose = set(meta.get("doa_mirror_normals") or {}) | set(meta.get("doa_axes") or {})
    return [a for a in others if a in loose or a not in with_doa], others


# ----------------------------------------------------------------------------------------------- together
def detections_from_diagnostics(diagnostics):
    """{array: (times, scores, events)} of the frontend's detections (diagnostics.json; event −1: unmatched)."""
    out = {}
    for name, a in (diagnostics or {}).get("arrays", {}).items():
        det = a.get("detections", [])
        out[name] = (np.array([d["time"] for d in det], float), np.array([d["score"] for d in det], float),
                     np.array([-1 if d.get("event") is None else int(d["event"]) for d in det], int))
    return out


def _doas_by_time(features, name, times, events):
    """{detection time: the frontend's DOA (3,) of its event, NaN if none} of array ``name`` (:func:`_doa_rows`,
    every row, doubted or not); None without features or detections."""
    if features is None or times is None or features.get("doa") is None:
        return None
    u = _doa_rows(features, name, np.asarray(events, int), ambiguous=True, allow=None)
    return dict(zip(np.asarray(times, float).tolist(), u))


def nlos_events(diagnostics, name):
    """The events whose arrival at array ``name`` the frontend flagged reflection-only ("nlos", diagnostics.json)."""
    arrivals = (diagnostics or {}).get("arrays", {}).get(name, {}).get("arrivals", [])
    return [int(r["event"]) for r, f in zip(arrivals, _flags(r.get("flag") for r in arrivals)) if "nlos" in f]


def matched_findings(session, diagnostics):
    """Arrays whose detections mostly match no event: events.csv's emission times do not fit this recording."""
    n = len(session["events"])
    out = []
    for name, a in (diagnostics or {}).get("arrays", {}).items():
        matched = sum(d.get("event") is not None for d in a.get("detections", []))
        if matched < MATCHED_FAIL * n and len(a.get("detections", [])) >= MATCHED_FAIL * n:
            out.append(Finding("failed", "events.csv", "events vs chirps", f"events.csv: only {matched} of {n} events "
                               f"match the {len(a['detections'])} chirps detected in {a.get('wav', name)}: are the "
                               "emission times from this session?", name))
    return out


def setup_findings(session, diagnostics=None, features=None, threshold=8.0):
    """Every set-up finding of a session (list of :class:`Finding`, the failed ones first).

    session : the in-memory session; diagnostics : the frontend's (its detections are reused; else the chirps
    are detected here); features : the features (speed of sound and the odometry's checks; skipped if None).
    """
    dets = detections_from_diagnostics(diagnostics)
    results, out, boards = {}, [], {}
    for a in session["arrays"]:
        times, scores, events = dets.get(a["name"], (None, None, None))
        clock_times = times   # every chirp times the clock (a reflection is milliseconds late, over seconds)
        if times is not None:
            # a reflection-only arrival (the frontend's "nlos") is no one plane wave of the chirp: paths of like
            # strength from several directions, whose inter-mic delays fit no geometry (lshape seed 12: a 6-mic
            # circle with 7 of its 16 arrivals such was failed as 0.71× too small; without them: no finding)
            direct = ~np.isin(events, nlos_events(diagnostics, a["name"]))
            times, scores, events = (times[direct], scores[direct], events[direct]) if direct.any() else \
                (times, scores, events)
        res = C.check_array(a, session, times, scores, threshold, clock_times=clock_times)
        doas = _doas_by_time(features, a["name"], times, events)
        found = channel_findings(a, res, session["speed_of_sound"], doas)
        if _geometry_failed(found) and res["n_detected"] > C.N_EVENTS:
            res = C.check_array(a, session, times, scores, threshold, n_events=CONFIRM_EVENTS,
                                clock_times=clock_times)
            found = channel_findings(a, res, session["speed_of_sound"], doas)
        results[a["name"]] = res
        out += found
        if not any(f.status == "failed" for f in found):
            boards[a["name"]] = _board_speed(a, res, session["speed_of_sound"], doas)
    out += clock_findings(session, results)
    out += identical_recordings(session)
    out += trajectory_findings(session["events"], features) + temperature_findings(session)
    if diagnostics is not None:
        out += matched_findings(session, diagnostics)
    if features is not None and not any(f.check in ("events vs chirps", "emission clock") for f in out):
        mics = {a["name"]: np.asarray(a["mics"], float).tolist() for a in session["arrays"]}
        named = {f.array for f in out if f.status == "failed"}  # the delays already explain those arrays
        features = {**features, "meta": {**features["meta"], "mics": mics}}
        chains = {}
        fits = speed_of_sound_fit(features, chains=chains)
        out = [_doa_vouched(f, features, chains) for f in out]
        board = board_sound({k: v for k, v in boards.items() if k not in named})
        sound = [f for f in sound_findings(features, fits, board=board, chains=chains)
                 if not (f.check == "geometry scale" and f.array in named)]
        out += sound
        if not sound and not _odometry_tested(features, fits):
            out += board_findings(board, session["speed_of_sound"], features)
        if board is not None and not any(f.check in ("speed of sound", "odometry scale") for f in out):
            out.append(_board_note(board, session["speed_of_sound"]))
    return sorted(out, key=lambda f: -STATUS_RANK[f.status])


def _odometry_tested(features, fits):
    """True where the arrivals and DOAs against the odometry test the declared speed of sound (:func:`_near_sound`:
    a source static during its sweeps, an array whose fit is usable). Its silence there outweighs one board's own c:
    the odometry's fit is ~10× the more precise (warehouse check seed 401, the right c: one tetrahedron read
    349.5 ± 2.2 m/s, 3σ, and named every array); the boards alone speak where it is off (a moving source's
    Doppler biases it) or has nothing to fit."""
    return not features["meta"].get("doa_time_s") and bool(_usable(fits))


def _doa_vouched(f, features, chains):
    """Finding ``f``, or — a whole-geometry failure ("geometry": the pair delays of the array's strongest chirps
    fit no plane wave on its declared mics) of an array whose DOAs fit the directions to the odometry's positions
    (with its arrivals, RMS ≤ DOA_TRUST σ over ≥ VOUCH_DOA_ROWS DOAs, those doubted for a reflection inside the
    gate or a spread peak kept) — the `suspect` direct-path finding. ``chains``: :func:`speed_of_sound_fit`'s.
    The frontend's SRP finds those DOAs on that same geometry: a wrong one bends them (a mirror, a shape, a mic
    order), while reflections bend the pair delays more, where the whitened band weighs a direct path from near
    the board's normal (small in-plane delays) no more than the larger delays of reflections from low elevations
    (moving seed 692's reference, the robot 53–89° above its plane: 9 of its 12 strongest chirps misfit by
    68–251 µs; its DOAs 0.8–6.1° from the truth, median 1.8°)."""
    chain = chains.get(f.array) if f.check == "geometry" and f.status == "failed" else None
    if chain is None:
        return f
    u = _doa_rows(features, f.array, chain.e_id, allow=SCALE_DOA_DOUBTS)
    n = int(np.sum(np.all(np.isfinite(u), axis=1)))
    misfit = _fit_one_array(*chain[:4], u, *_sigmas(features["meta"]), starts=chain.starts)[3] \
        if n >= VOUCH_DOA_ROWS else np.inf
    if not misfit <= DOA_TRUST:
        return f
    return replace(f, status="suspect", check="direct path", text=f"{f.text.removesuffix(WRONG_GEOMETRY)}, but its "
                   f"DOAs on this geometry fit the directions to the odometry's positions ({misfit:.1f}σ over {n} "
                   "chirps), which a wrong geometry's would not: reflections bend most chirps' inter-mic delays (a "
                   "wall or an obstacle near it, or the speaker near its normal?); its arrivals are doubtful")


def _directions(doas, times):
    """(K, 3) the frontend's DOA at each chirp ``times`` ({detection time: (3,)}, NaN rows where none), or None."""
    return None if doas is None else np.array([doas.get(t, (np.nan,) * 3) for t in times], float)


def _board_speed(a, res, c0, doas):
    """:func:`calib.frontend.consistency.board_speed` of array ``a`` from its :func:`check_array` result ``res``
    (None: a planar or linear board, no chirps, too few agreeing events)."""
    d = res["delays"]
    if d is None or not len(d.times):
        return None
    directions = _directions(doas, d.times)
    return C.board_speed(d, np.asarray(a["mics"], float), c0, directions)


def board_sound(boards):
    """(c, std, names) of the 3-D boards' own speed of sound ({array: :class:`~calib.frontend.consistency.
    BoardSpeed` or None}), their weighted mean (:func:`_sound_mean`: boards that disagree widen it); None if no
    board measured one."""
    got = {k: (b.c, b.std) for k, b in boards.items() if b is not None}
    if not got:
        return None
    c, sd, _ = _sound_mean(got)
    return c, sd, tuple(sorted(got))


def sound_cause(c_hat, sd, c0, board):
    """Which of the two the boards' own delays blame when the arrivals against the odometry say ``c_hat`` ± ``sd``
    m/s where ``c0`` is declared (they fix only c / the odometry's scale): "sound" (the board agrees with
    ``c_hat``, not with ``c0``), "odometry" (the reverse: the odometry is mis-scaled) or None (no board, or it
    cannot tell: both or neither within BOARD_SIGMA). board: :func:`board_sound`'s (c, std, names) or None."""
    if board is None:
        return None
    c_b, sd_b, _ = board
    with_odo = abs(c_b - c_hat) <= BOARD_SIGMA * np.hypot(sd, sd_b)
    with_decl = abs(c_b - c0) <= BOARD_SIGMA * sd_b
    return "sound" if with_odo and not with_decl else "odometry" if with_decl and not with_odo else None


def board_findings(board, c0, features, source="session.toml"):
    """The declared speed of sound against the 3-D boards' own (:func:`board_sound`) where the odometry's test is
    off (a source moving during its sweeps: :func:`_near_sound` is off; nothing to fit: :func:`_odometry_tested`):
    beyond BOARD_SIGMA of the board's and SOUND_NEAR_TOL, `suspect`, every non-reference array named (their ranges from the reference
    scale with c / c0). [] otherwise. The board's declared size is the other reading (a board 2 % smaller than
    declared reads c 2 % slow): said."""
    if board is None or abs(board[0] / c0 - 1) <= SOUND_NEAR_TOL or abs(board[0] - c0) <= BOARD_SIGMA * board[1]:
        return []
    rel = board[0] / c0 - 1
    names = _non_reference(features)
    return [Finding("suspect", source, "speed of sound", f"{source}: speed_of_sound = {c0:g} m/s, but "
                    f"{_board_text(board)} ({100 * rel:+.1f} %, {abs(board[0] - c0) / board[1]:.0f}σ): every array's "
                    f"distance from the reference is scaled by it (about {abs(100 * rel):.1f} cm per metre; named: "
                    f"{', '.join(names)}); set it to the air's at the session's temperature (331.3 + 0.606·T °C) — or, "
                    f"if it is right, measure the board{'s' if len(board[2]) > 1 else ''}: "
                    f"{abs(100 * rel):.1f} % {'larger' if rel > 0 else 'smaller'} than declared", arrays=names)]


def _board_note(board, c0):
    """A `note` of the 3-D boards' own c (:func:`board_sound`) where no speed-of-sound finding was made: the
    estimate's own check of c (``calib.estimator.soundspeed.speed_check``, far more precise than this stage's fit)
    may still ask for another c, and the boards then tell which of the two it is (:func:`odometry_blamed`)."""
    return Finding("note", "session.toml", "board speed", f"{_board_text(board)}, the declared {c0:g} m/s "
                   f"{abs(board[0] - c0) / board[1]:.1f}σ away", reading=(float(board[0]), float(board[1]),
                                                                       tuple(board[2])))


def _board_text(board):
    c_b, sd_b, names = board
    return (f"the mic delays of the 3-D board{'s' if len(names) > 1 else ''} {', '.join(names)} (their declared "
            f"geometry in metres, no odometry) say {c_b:.1f} ± {sd_b:.1f} m/s")


def folder_findings(folder, mics=None, threshold=8.0):
    """:func:`setup_findings` of a session folder, its features extracted here (a notebook's one call).
    mics : {array: (M, 3) m} replacing session.toml's (what-if: a board declared at another size)."""
    from calib.frontend import extract_features
    from calib.pipeline.formats.session import read_session

    session = read_session(folder)
    for a in session["arrays"]:
        if a["name"] in (mics or {}):
            a["mics"] = np.asarray(mics[a["name"]], float)
    features, diagnostics = extract_features(session, threshold=threshold)
    return setup_findings(session, diagnostics, features, threshold)


def feature_findings(features):
    """The set-up findings a features folder alone can show (``calib estimate``: no recordings): the speed of
    sound and the odometry against the arrivals and DOAs, mirrored DOAs, the trajectory. Dicts, as
    :func:`stage_findings`."""
    found = sound_findings(features, source="meta.json") + trajectory_findings(features["events"], features)
    return [f.as_dict() for f in sorted(found, key=lambda f: -STATUS_RANK[f.status])]


def apply_findings(calib, findings):
    """The calibration dict with the set-up ``findings`` (dicts) in its report (``setup``) and ranked first
    in its verdict (``calib.estimator.verdict.with_setup``); unchanged when there are none."""
    from calib.estimator.verdict import with_setup

    if not findings:
        return calib
    rep = calib["report"]
    findings = settled_by_estimate(findings, rep)
    verdict = odometry_blamed(rep.get("verdict", {}), findings, rep)
    return {**calib, "report": {**rep, "verdict": with_setup(verdict, findings), "setup": list(findings)}}


def odometry_blamed(verdict, findings, report):
    """The estimator's verdict with the arrays its speed-of-sound check named alone (report.json
    ``speed_of_sound.check.added``, ``calib.estimator.verdict.name_speed``: c fixed, the data asking for
    another) given back where the 3-D boards blame the odometry's scale instead: a set-up finding ``odometry
    scale``, or their own c (the ``board speed`` note) within BOARD_SIGMA of the declared one and beyond it of the
    data's (:func:`sound_cause`). The declared c then places those arrays right (lab 522 with its odometry 2 %
    long: 0.3-0.6 cm). Where the boards side with the data's c the reason says so. Returns a new dict
    (``verdict`` when nothing changes)."""
    check = (report.get("speed_of_sound") or {}).get("check") or {}
    if not check.get("added"):
        return verdict
    c0 = check["declared_m_s"]
    board = next((tuple(f["reading"]) for f in findings if f.get("check") == "board speed" and f.get("reading")), None)
    cause = "odometry" if any(f.get("check") == "odometry scale" for f in findings) else \
        sound_cause(check["fitted_m_s"], c0 * check["std_relative"], c0, board)
    if cause is None:
        return verdict
    said = "the 3-D boards' own c (set-up: " + (_board_text(board) if board else "odometry scale") + ")"
    if cause == "sound":
        why = f" — {said} agrees with the data's, not the declared one: the declared c is off"
        return {**verdict, "reasons": [r + why if r.startswith("the speed of sound") else r
                                       for r in verdict.get("reasons", [])]}
    why = f" — {said} agrees with the declared one: the odometry's scale is off, the arrays are right, not named"
    back = set(check["added"])
    return {**verdict, "reasons": [r + why if r.startswith("the speed of sound") else r
                                   for r in verdict.get("reasons", [])],
            "status": check.get("status_before", verdict.get("status")),
            "flagged_arrays": [a for a in verdict.get("flagged_arrays", []) if a not in back]}


def settled_by_estimate(findings, report):
    """The trajectory findings that name an array's possible mirror image (:func:`trajectory_findings`, from the
    odometry's shape alone) made notes where the estimate refitted that mirror against the data
    (``calib.estimator.ambiguity``, report.json ``stages.mirror_basins``) and it was not a second solution:
    clearly worse (or clearly better, and taken). An array the estimate left ambiguous keeps its finding (the
    verdict names it too). A speed-of-sound finding says the c the estimate solved (report.json
    ``speed_of_sound``), its status kept. Returns a new list of dicts."""
    tried = {m["array"]: m for m in (report.get("stages") or {}).get("mirror_basins", [])}
    speed = report.get("speed_of_sound") or {}
    out = []
    for f in findings:
        if f.get("check") == "speed of sound" and speed.get("estimated"):
            # the estimate solved c (estimator/soundspeed.py): said, the status kept — the data fix c only against
            # the odometry's scale, and a wheel-diameter error reads the same
            f = {**f, "text": f"{f['text']} (the estimate solved it: {speed['value_m_s']:.1f} ± {speed['std_m_s']:.1f} "
                              "m/s, the arrays placed with it: right if the odometry's distances are metric)"}
        if f.get("check") == "odometry scale" and f.get("status") == "suspect" and not speed.get("estimated"):
            # the boards blamed the odometry and c stayed declared: the arrivals, not the odometry, set the metre
            # (lab 522 with its odometry 2 % long: arrays 0.3-0.6 cm off with c fixed, 2-6 cm with c solved)
            f = {**f, "arrays": [], "text": f"{f['text']} (the estimate kept the declared speed of sound: the arrays "
                                             "are placed by the arrivals' metre, not the odometry's)"}
        m = tried.get(f.get("array"))
        if f.get("check") == "trajectory" and f.get("status") == "suspect" and m is not None and not m["ambiguous"]:
            how = "taken: it fits better" if m["switched"] else "excluded: it fits worse"
            f = {**f, "status": "note", "text": f"{f['text']} (the estimate refitted that mirror {m['position_m']:.2f} m "
                                                f"away and the data decide: {how} by {abs(m['dcost']):.1f} in cost)"}
        out.append(f)
    return out


def stage_findings(session, out, threshold=8.0):
    """:func:`setup_findings` for ``calib run`` after its features stage: the detections of OUT/diagnostics and
    the features of OUT/features are reused. Returns the findings as dicts (JSON-able)."""
    import json
    from pathlib import Path

    from calib.pipeline.formats.io import read_features
    from calib.pipeline.headerrate import with_rates

    out = Path(out)
    try:
        diag = json.loads((out / "diagnostics" / "diagnostics.json").read_text())
    except (OSError, ValueError):
        diag = None
    feats = read_features(out / "features")
    fixed = feats["meta"].get("header_rates") or {}
    found = setup_findings(with_rates(session, fixed), diag, feats, threshold)   # (the samples as extracted)
    return [f.as_dict() for f in sorted(header_rate_findings(session, fixed) + found,
                                        key=lambda f: -STATUS_RANK[f.status])]


def header_rate_findings(session, fixed):
    """``suspect`` findings for the arrays the features stage took at a measured rate instead of their WAV
    header's (features/meta.json ``header_rates``, pipeline/headerrate.py)."""
    out = []
    for a in session["arrays"]:
        f = fixed.get(a["name"])
        if f and f.get("fast_clock"):
            out.append(Finding("note", _wav(a), "sample rate", f"{_wav(a)} (array {a['name']}): its clock runs "
                               f"{1e6 * (f['scale'] - 1):+.0f} ppm against the emission times "
                               f"({f['header'] * f['scale']:.1f} Hz for its header's {f['header']} Hz; more than a "
                               f"crystal drifts): its samples taken "
                               f"at {f['used']} Hz (its offset and drift are relative to that rate)", a["name"]))
        elif f:
            out.append(Finding("suspect", _wav(a), "sample rate", f"{_wav(a)} (array {a['name']}): the header's "
                               f"sample rate {f['header']} Hz is wrong: the chirps' spacing says "
                               f"{f['header'] * f['scale']:.0f} Hz ({100 * (f['scale'] - 1):+.2f} %, far beyond a "
                               f"clock drift); calibrated with its samples at {f['used']} Hz. Declare it (sample_rate "
                               f"= {f['used']} in its [[arrays]] table of session.toml) or rewrite the header",
                               a["name"]))
    return out


def explain_failure(session, exc, threshold=8.0):
    """The InputError to raise when the features of a session could not be extracted (``exc``): the set-up
    findings that explain it first (a wrong sample rate, another session's events.csv), else ``exc``."""
    from calib.errors import InputError

    try:
        found = [f for f in setup_findings(session, threshold=threshold) if f.status == "failed"]
    except InputError:
        return exc
    if not found:
        return exc
    more = f" (+{len(found) - 1} more set-up finding(s): calib check lists them)" if len(found) > 1 else ""
    return InputError(f"{found[0].text}{more}; then: {exc}")
