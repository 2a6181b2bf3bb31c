"""Signal-level set-up checks of one array's recording: do its channels fit the declared mic geometry?

A wiring or typing mistake in the set-up (a dead mic, two channels swapped, a mic wired with inverted
polarity, coordinates in cm typed as m, a circle declared as a line) leaves the delays between the mics of
one array inconsistent with the declared rigid geometry, which any plane wave must satisfy:
``t_m − t_n = −(p_m − p_n)·w`` with ``w = u / c`` (``u`` toward the source, ``p`` the mic positions). This
module measures those delays on the strongest chirps and names the channel or the scale that does not fit.

Per array (:func:`check_array`):
1. the chirps are detected as the frontend does (:mod:`calib.frontend.detect`, on the channel sum), or the
   caller's detections are used; the ``N_EVENTS`` strongest are kept;
2. each channel is matched-filtered with the chirp, gated around the direct path (the strongest peak of
   the summed envelope), and every mic pair cross-correlated (PHAT, the chirp's band) → the pair's delay,
   the sign of its peak (a negative peak: one of the two is inverted) and the channel energies;
3. :func:`fit_geometry`: per event a plane wave fitted to the pair delays with the declared geometry; the
   misfit against the array's own scale, the leave-one-out and swapped-pair fits, the scale ``|w|·c``.

What the delays cannot show (docs/reliability.md, "Set-up mistakes"): any orthogonal transform of the
geometry (a relabelling that is a symmetry of the array, a rotation, a mirror) fits exactly as well, since
the direction ``w`` is free per event. Mirrors are observable only through the DOAs against the other
arrays (the estimator's residuals).

Every function returns plain data; the pipeline (``calib.pipeline.setupcheck``) turns it into findings.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from calib.robust import mad_std

from .detect import matched_envelope, pick_peaks, refine_peak
from .signals import ArrayAudio, band_weights, chirp_band, chirp_template

N_EVENTS = 12             # strongest chirps whose inter-mic delays are measured
MAX_BOARD_M = 0.5         # m: no single board is wider; bounds the lag search when the declared size is wrong
MIN_BOARD_M = 0.15        # m: the lag search covers at least this (a geometry declared too small)
GATE_FLAT_PULSES = 1.5    # the gate is flat over the largest pair delay plus this many pulse widths (1 / band)
UPSAMPLE = 8              # cross-correlation interpolation factor (before the parabolic refinement)
DEAD_DB = -30.0           # a channel this far below the array's median energy in the chirps is dead
WEAK_DB = -12.0           # ... this far below: weak (a loose connector, a covered mic)
PLATEAU_RUN = 4           # samples: a run of equal values at least this long near the peak level is clipping
CLIP_LEVEL = 0.9          # ... near the peak: above this fraction of the channel's largest magnitude
CLIP_FRACTION = 0.005     # fraction of the chirp samples on such plateaus above which a channel is clipped
INVERTED_FRACTION = 0.75  # a mic whose pair peaks are negative in more than this fraction: inverted
MISFIT_QUANTILE = 0.3     # the events' misfit that judges a geometry: most events (not all) must fit it
MISFIT_FAIL = 0.15        # misfit RMS over the array's largest measured delay: the geometry does not fit
MISFIT_NAMED = 0.02       # ... above this, a fix that cuts it by FIX_NAMED names the channel (clean: < 0.005)
FIX_NAMED = 5.0
MISFIT_FLOOR_S = 3e-6     # s: below this absolute misfit a geometry always fits (clean rooms: 0.1-1.2 µs)
MISFIT_BEST_K = 3         # a geometry that this many events fit within MISFIT_NAMED is the board's: a wrong one
                          # fits no event, reflections bend only some (a moving robot's reference array in a
                          # reverberant lab: 3 of 12 chirps at 1.4-1.9 %, the other 9 at 17-58 %)
MOVE_ITERATIONS = 8        # alternating least squares that refit one mic's position (converged in 3-5)
FIX_RATIO = 3.0           # a fix (a swap, leaving a mic out) must cut the misfit by this factor to be named
SCALE_FAIL = 1.6          # |w|·c (the declared size's inverse scale) off 1 by more than this factor
SCALE_FAIL_3D = 1.15      # ... a 3-D array's, agreed on by CONSENSUS_SUPPORT of its events (clean: ≤ 1.11)
CONSENSUS_TOL = 0.05      # relative: events whose |w|·c agree this well agree on the scale (clean: ~1 %)
CONSENSUS_SUPPORT = 0.4
PLANAR_TOP_TOL = 0.1      # a planar array's largest |w|·c above 1 counts when PLANAR_TOP_MIN events lie within this
PLANAR_TOP_MIN = 3        # (relative) below it: a size declared too small lifts all; a warehouse's reflections put
                          # lone ones there (1.28, 1.63, 1.81 beside 0.86-0.98: read as 0.61 × too small by the largest)
SCALE_SCATTER_K = 1.0     # a 3-D array's scale bound widened by this × its events' scatter (robust std of log |w|·c):
# small arrays at low rates read the delays long in reverberant rooms (a 4 cm tetrahedron at 16 kHz in a 1.2 s
# warehouse at 5 dB: |w|·c 0.84-1.30, consensus 1.17, std 0.09; a clean lab: ≤ 1.11, std ~0.01)
DIRECTION_AGREE_DEG = 10.0   # a 3-D array's event that says the board is too small (|w|·c > 1) testifies only if its
# plane wave points within this of the frontend's DOA: a size error scales w, not its direction. Delays that pair one
# mic's direct path with another's reflection do not (warehouse 403's 4 cm tetrahedron: 7 of 16 events at |w|·c
# 1.50-1.54 whose w pointed 40-90° away from DOAs right to 1°, a false "0.66× too small"; its true plane waves
# within 10° of the DOAs)
# A 3-D board's speed of sound (board_speed): the declared mic positions against the delays
BOARD_MIN_EVENTS = 6      # events that must agree on |w| (within CONSENSUS_TOL) for a board's c ...
BOARD_SUPPORT = 0.5       # ... and at least this fraction of those whose plane wave points at the DOA
BOARD_MIC_TOL_M = 3e-4    # m: each mic's acoustic centre vs its declared position (PCB placement, the MEMS port);
# the fitted size's error is this over (RMS radius · √M): 0.4 % for a 3.5 cm tetrahedron
BOARD_SCATTER_FLOOR = 0.003   # relative: the events' scatter taken as at least this (a near source's curvature:
# 0.3 % per event at 2 m on a 3.5 cm tetrahedron; the MAD of a few nearly equal values can be ~0)
BOARD_BIAS = 0.002        # relative: residual bias of the delays (the gate: 0.07 %; a source at 2 m: +0.08 %)


@dataclass(frozen=True)
class PairDelays:
    """Inter-mic delays of one array on its strongest chirps.

    pairs : (P, 2) int mic indices (m, n), m < n. tau : (K, P) s, ``t_m − t_n``. sign : (K, P) ±1, the sign of
    the cross-correlation peak. coherence : (K, P) normalised peak height in [0, 1]. energy : (K, M) matched
    filter energy of each channel in the gated direct path. plateau : (M,) fraction of the chirp samples on
    clipping plateaus. identical : list of (m, n) channel pairs with identical samples. times : (K,) s, the
    chirps' detection times used. fs : Hz. tau_flat : (K, P) s, a 3-D board's delays through a flat-topped gate
    (:func:`flat_taper`; None for another board): unbiased, for :func:`board_speed`; ``tau`` (a Hann gate, which the geometry checks'
    thresholds were set on) reads every delay short by a fraction (0.9 % on a 3.5 kHz band).
    """
    pairs: np.ndarray
    tau: np.ndarray
    sign: np.ndarray
    coherence: np.ndarray
    energy: np.ndarray
    plateau: np.ndarray
    identical: list
    times: np.ndarray
    fs: float
    digest: str = ""
    tau_flat: np.ndarray | None = None


@dataclass(frozen=True)
class GeometryFit:
    """:func:`fit_geometry`'s result. misfit : s, the RMS pair residual of the events (:func:`_misfit`); ratio : misfit
    over the largest measured pair delay; scale : the factor by which the declared geometry is too large
    (1 = right; NaN if not measurable); loo : {mic: misfit without it}; moved : {mic: (misfit, offset (3,) m)
    with that mic's position refitted}; swaps : {(m, n): misfit with the two swapped}; used : mics in the fit; support : the fraction of the events that agree on the scale (a 3-D
    array: :func:`consensus`; a planar or linear one: those with ``|w|·c > 1``, which only a geometry declared
    too small gives, 0 when their top is not supported: :func:`supported_top`); scatter : a 3-D array's robust std of ``log |w|·c`` over its
    events (noise and reflections; 0 for a planar one); best : s, the MISFIT_BEST_K-th smallest event misfit."""
    misfit: float
    ratio: float
    scale: float
    span: float
    used: tuple = ()
    support: float = np.nan
    loo: dict = field(default_factory=dict)
    swaps: dict = field(default_factory=dict)
    moved: dict = field(default_factory=dict)
    scatter: float = 0.0
    best: float = np.nan


# ----------------------------------------------------------------------------------------------- detection
def detect_chirps(x, template, fs, band, t_emit, threshold=8.0):
    """Detection times (s, local clock) and scores of the chirps in recording ``x`` (the frontend's detector:
    matched envelope of the channel sum, peaks above ``threshold`` × the local background)."""
    env, dec = matched_envelope(x.channel_sum(), template, fs, band)
    env_rate = fs / dec
    dur = len(template) / fs
    spacing = np.min(np.diff(t_emit)) if len(t_emit) > 1 else np.inf
    idx, score = pick_peaks(env, env_rate, min(dur, 0.5 * spacing), threshold)
    return (refine_peak(env, idx) / env_rate if len(idx) else np.zeros(0)), np.asarray(score, float)


def clock_scale(det_t, t_emit, tol=2e-3, lo=0.5, hi=2.0):
    """The ratio (local clock rate / emission clock rate) that best aligns the detections with the emission
    pattern, whatever its size (the association only searches |δ| ≤ 1e-3): the mode of the interval ratios
    ``(d_b − d_a) / (e_b − e_a)`` over all pairs, in log bins of ``tol``. Returns (scale, support): support
    is the fraction of the emission pairs that agree (1 = every interval matched). NaN when < 3 detections."""
    d, e = _first_block(np.sort(np.asarray(det_t, float)), np.sort(np.asarray(t_emit, float)))
    if len(d) < 3 or len(e) < 3:
        return float("nan"), 0.0
    dd = (d[None, :] - d[:, None])[np.triu_indices(len(d), 1)]
    de = (e[None, :] - e[:, None])[np.triu_indices(len(e), 1)]
    de = de[de > 0]
    r = np.log(np.abs(dd)[:, None] / de[None, :]).ravel()
    r = r[(r > np.log(lo)) & (r < np.log(hi))]
    if not r.size:
        return float("nan"), 0.0
    bins = np.floor(r / tol).astype(np.int64)
    vals, counts = np.unique(np.concatenate([bins, bins + 1]), return_counts=True)  # overlapping bins
    best = vals[np.argmax(counts)]
    sel = r[(bins == best) | (bins == best - 1)]
    return float(np.exp(np.median(sel))), float(len(sel) / len(de))


CLOCK_BLOCK = 40   # clock_scale compares the intervals of at most this many chirps (detections, emissions)


def _first_block(d, e):
    """(detections, emissions) that :func:`clock_scale` compares: the first CLOCK_BLOCK of each (all when
    fewer). Every pair of intervals is one ratio, O(D² E²): 0.9 s for 90 events and 25 s for 200, per array,
    on every features run (pipeline/headerrate.py); 40 bound it at ~0.6e6 ratios (~10 ms), and a wrong rate
    shows in any block of consecutive chirps (the straight-line refinement then uses them all)."""
    return d[:CLOCK_BLOCK], e[:CLOCK_BLOCK]


# ----------------------------------------------------------------------------------------------- delays
def _lag_bound(mics, c):
    """Largest |pair delay| searched (s): the declared size, clipped to what a board can be."""
    d = np.max(np.linalg.norm(mics[:, None] - mics[None], axis=-1)) if len(mics) > 1 else 0.0
    return float(np.clip(1.2 * d, MIN_BOARD_M, MAX_BOARD_M) / c)


def _plateau_fraction(seg):
    """(M,) fraction of each channel's samples lying on runs of ≥ PLATEAU_RUN equal values above CLIP_LEVEL ×
    its largest magnitude: a digital rail or a limiter (a clean signal, even quantised, rarely repeats a value
    near its peak more than twice)."""
    out = np.zeros(seg.shape[0])
    for m, x in enumerate(seg):
        peak = np.max(np.abs(x))
        if peak <= 0:
            continue
        same = np.r_[False, x[1:] == x[:-1]]
        high = np.abs(x) >= CLIP_LEVEL * peak
        flag = same & high
        # run lengths of consecutive flagged samples (each run of k equal values gives k − 1 flags)
        edges = np.diff(np.r_[0, flag.astype(np.int8), 0])
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        runs = stops - starts + 1
        out[m] = np.sum(runs[runs >= PLATEAU_RUN]) / len(x)
    return out


def _matched(seg, template, fs, band, n_lags):
    """(M, n_lags) real band-limited matched-filter outputs of ``seg`` (M, L) and their summed envelope."""
    L = seg.shape[1]
    nfft = int(2 ** np.ceil(np.log2(L + len(template))))
    f = np.fft.rfftfreq(nfft, 1 / fs)
    spec = np.fft.rfft(seg, nfft, axis=-1) * np.conj(np.fft.rfft(template, nfft)) * band_weights(f, band)
    r = np.fft.irfft(spec, nfft, axis=-1)[:, :n_lags]
    analytic = np.fft.ifft(np.concatenate([spec, np.zeros((len(seg), nfft - spec.shape[1]))], axis=-1) * 2,
                           axis=-1)[:, :n_lags]
    return r, np.sum(np.abs(analytic), axis=0)


def _pair_lags(g, fs, band, max_lag):
    """PHAT cross-correlation of every pair of gated pulses ``g`` (M, W): (P, 2) pairs, lags (P,) s, signed
    peak heights (P,) normalised to [−1, 1]."""
    m, w = g.shape
    nfft = int(2 ** np.ceil(np.log2(2 * w)))
    f = np.fft.rfftfreq(nfft, 1 / fs)
    wts = band_weights(f, band)
    G = np.fft.rfft(g, nfft, axis=-1)
    pairs = np.array(list(combinations(range(m), 2)), int).reshape(-1, 2)
    cross = G[pairs[:, 0]] * np.conj(G[pairs[:, 1]])
    cross = wts * cross / np.maximum(np.abs(cross), 1e-30)
    n_up = nfft * UPSAMPLE
    cc = np.fft.irfft(cross, n_up, axis=-1) * n_up / max(2 * np.sum(wts), 1e-30)  # 1 = fully coherent
    k = int(np.ceil(max_lag * fs * UPSAMPLE))
    win = np.concatenate([cc[:, -k:], cc[:, : k + 1]], axis=-1)  # lags −k .. k (upsampled samples)
    best = np.argmax(np.abs(win), axis=-1)
    peak = win[np.arange(len(pairs)), best]
    y = np.abs(win)
    b = np.clip(best, 1, win.shape[1] - 2)
    a0, a1, a2 = y[np.arange(len(pairs)), b - 1], y[np.arange(len(pairs)), b], y[np.arange(len(pairs)), b + 1]
    den = a0 - 2 * a1 + a2
    off = np.where(den < 0, 0.5 * (a0 - a2) / np.where(den < 0, den, -1.0), 0.0)
    lag = (b + np.clip(off, -0.5, 0.5) - k) / (fs * UPSAMPLE)
    return pairs, lag, np.clip(peak, -1.0, 1.0)


def flat_taper(n, flat):
    """(n,) gate window: 1 within ``flat`` samples of its centre, a raised-cosine roll-off to 0 beyond. A taper
    across the pulses themselves (a Hann window over the whole gate) pulls each pulse toward the gate's centre
    and shrinks every pair delay by the same fraction: 0.9 % on a 3.5 kHz chirp band, 0.5 % on 9.5 kHz, measured on
    exact plane waves (tests/test_board_speed.py) — a 3-D board's speed of sound (:func:`board_speed`) read that
    much fast; the flat top leaves 0.07 %. (The geometry checks keep the Hann gate: a flat one lets a wall's
    reflection in at full weight, robot seed 500's wall-mounted 6-mic circle then misfit 23 %: a false finding.)"""
    x = np.abs(np.arange(n) - (n - 1) / 2)
    edge = max((n - 1) / 2 - flat, 1.0)
    return np.where(x <= flat, 1.0, 0.5 + 0.5 * np.cos(np.pi * np.clip((x - flat) / edge, 0.0, 1.0)))


def measure_delays(x, mics, template, fs, band, times, c):
    """:class:`PairDelays` on the chirps detected at ``times`` (s) in recording ``x`` ((M, N), sliceable)."""
    mics = np.asarray(mics, float)
    max_lag = _lag_bound(mics, c)
    pulse = 1.0 / (band[1] - band[0])
    half = int(np.ceil((max_lag + 3 * pulse) * fs))
    pre = 2 * half + int(0.02 * fs)  # the direct path may precede the strongest peak a little
    n_lags = 2 * pre
    taper = np.hanning(2 * half + 1)
    # (the flat gate's delays serve a 3-D board's own c only: board_speed)
    flat = flat_taper(2 * half + 1, (max_lag + GATE_FLAT_PULSES * pulse) * fs) if is_volume(mics) else None
    taus, flats, signs, cohs, energies, plateau, identical = [], [], [], [], [], [], set()
    for t in times:
        s0 = int(round(t * fs)) - pre
        seg = np.asarray(x[:, s0 : s0 + n_lags + len(template)], np.float64)
        plateau.append(_plateau_fraction(seg[:, pre : pre + len(template)]))
        identical |= {(a, b) for a, b in combinations(range(len(seg)), 2)
                      if np.any(seg[a]) and np.array_equal(seg[a], seg[b])}
        r, env = _matched(seg, template, fs, band, n_lags)
        p = int(np.argmax(env[half : n_lags - half])) + half
        g = r[:, p - half : p + half + 1] * taper
        pairs, lag, peak = _pair_lags(g, fs, band, max_lag)
        taus.append(lag)
        if flat is not None:
            flats.append(_pair_lags(r[:, p - half : p + half + 1] * flat, fs, band, max_lag)[1])
        signs.append(np.sign(peak))
        cohs.append(np.abs(peak))
        energies.append(np.sum(g**2, axis=1))
    m = len(mics)
    pairs = np.array(list(combinations(range(m), 2)), int).reshape(-1, 2)
    k = len(taus)
    return PairDelays(pairs=pairs, tau=np.array(taus).reshape(k, len(pairs)),
                      sign=np.array(signs).reshape(k, len(pairs)), coherence=np.array(cohs).reshape(k, len(pairs)),
                      energy=np.array(energies).reshape(k, m),
                      plateau=np.max(plateau, axis=0) if plateau else np.zeros(m), identical=sorted(identical),
                      times=np.asarray(times, float), fs=float(fs),
                      tau_flat=None if flat is None else np.array(flats).reshape(k, len(pairs)))


# ----------------------------------------------------------------------------------------------- fits
def _event_misfits(tau, pairs, mics, use):
    """(K,) each event's RMS pair residual of its plane-wave fit over the pairs of mics ``use``, and the
    per-event fitted ``w`` (K, 3)."""
    sel = np.isin(pairs[:, 0], use) & np.isin(pairs[:, 1], use)
    A = -(mics[pairs[sel, 0]] - mics[pairs[sel, 1]])  # (P', 3)
    y = tau[:, sel].T  # (P', K)
    w, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ w
    return np.sqrt(np.mean(res**2, axis=0)), w.T


def _misfit(tau, pairs, mics, use):
    """The MISFIT_QUANTILE over events of :func:`_event_misfits`, and the per-event ``w`` (K, 3). A wrong
    geometry misfits every event; a reflection stronger than the direct path (a reverberant room, a
    wall-mounted board) only some."""
    r, w = _event_misfits(tau, pairs, mics, use)
    return float(np.quantile(r, MISFIT_QUANTILE)), w


def _moved(tau, pairs, mics, use, m, iters=MOVE_ITERATIONS):
    """:func:`_misfit` with mic ``m``'s position refitted (the events' plane waves and one offset of that mic,
    by alternating least squares); and the offset (3,) m. A typed-in coordinate that is off is such an offset
    in every event; a pair delay that a reflection bent in some events is not."""
    p, delta = mics.copy(), np.zeros(3)
    sel = np.isin(pairs[:, 0], use) & np.isin(pairs[:, 1], use)
    pr, y = pairs[sel], tau[:, sel]
    sign = (pr[:, 0] == m).astype(float) - (pr[:, 1] == m)  # tau = -(p_a - p_b)·w: mic m's share, per pair
    for _ in range(iters):
        misfit, w = _misfit(tau, pairs, p, use)
        res = y + w @ (p[pr[:, 0]] - p[pr[:, 1]]).T  # (K, P') residual with the current geometry
        J = (sign[None, :, None] * w[:, None, :]).reshape(-1, 3)  # d res / d delta
        step, *_ = np.linalg.lstsq(J, -res.reshape(-1), rcond=None)
        delta = delta + step
        p[m] = mics[m] + delta
    return _misfit(tau, pairs, p, use)[0], delta


def _rank(mics, tol=1e-3):
    """Dimension spanned by the mics (1 linear, 2 planar, 3 volume): a plane wave's unknowns."""
    sv = np.linalg.svd(mics - mics.mean(axis=0), compute_uv=False)
    return int(np.sum(sv > tol * max(sv[0], 1e-12)))


def is_volume(mics):
    """True for a board whose mics span 3-D well (its thinnest extent over 0.1 of its widest): its delays measure
    the whole slowness, |w| = 1 / c; a (nearly) planar or linear one sees only its in-plane part."""
    sv = np.linalg.svd(mics - mics.mean(axis=0), compute_uv=False)
    return bool(len(sv) == 3 and sv[-1] > 0.1 * sv[0])


def supported_top(x, tol=PLANAR_TOP_TOL, n=PLANAR_TOP_MIN):
    """The largest value of ``x`` with at least ``n`` values (itself included) within a relative ``tol`` below
    it; NaN if none. A planar array's |w|·c above 1: the events nearest its plane tell a size declared too
    small (cos el / scale), and there are several of them; a lone high value is a reflection or noise."""
    x = np.sort(np.asarray(x, float))[::-1]
    for v in x:
        if np.sum((x <= v) & (x >= v / (1.0 + tol))) >= n:
            return float(v)
    return np.nan


def consensus(x, tol=CONSENSUS_TOL):
    """The value most of ``x`` (> 0) agree on, within a relative ``tol``: the median of the largest group
    within ±tol of one of them, and that group's fraction of ``x``. A 3-D array's scale ``|w|·c`` per event:
    with 4 mics every event fits a plane wave exactly (3 delays, 3 unknowns), so an event whose direct path a
    reflection hid shows only as a wrong ``|w|·c`` (0.1–3 in reverberant rooms), never as a misfit."""
    lx = np.log(np.asarray(x, float)[np.asarray(x, float) > 0])
    if not lx.size:
        return np.nan, 0.0
    group = _largest_group(lx, tol)
    return float(np.exp(np.median(group))), float(group.size / len(lx))


def _largest_group(lx, tol):
    """The largest group of the logs ``lx`` (n,) within ±log(1 + tol) of one of them (empty for none)."""
    near = np.abs(lx[:, None] - lx[None, :]) <= np.log1p(tol)
    return lx[near[int(np.argmax(near.sum(axis=1)))]] if lx.size else lx


def fit_geometry(delays, mics, c, exclude=(), directions=None):
    """Fit the declared geometry ``mics`` (M, 3) to the measured pair delays (:class:`PairDelays`): the plane
    wave of each event is free, so the misfit measures the geometry only (:class:`GeometryFit`).

    scale: the declared geometry is ``scale`` × too large. A 3-D array measures it from every event
    (``1 / |w| c``, the value the events agree on: :func:`consensus`); a planar (or linear) one only sees the
    in-plane part of ``w``, so ``|w| c ≤ 1``: the events above 1, when many, say it is too small (the largest
    but one: the source nearest the plane, an outlier spared), else the largest is only a bound (exact for a source in the plane; its odometry tells the rest:
    ``calib.pipeline.setupcheck.geometry_scale_fit``). directions : (K, 3) the frontend's DOA of each event in the
    array's frame (unit; NaN rows unknown), or None: a 3-D array's events above |w|·c = 1 whose plane wave points
    elsewhere (:data:`DIRECTION_AGREE_DEG`) do not testify to its size."""
    mics = np.asarray(mics, float)
    use = tuple(m for m in range(len(mics)) if m not in exclude)
    span = float(np.max(np.abs(delays.tau))) if delays.tau.size else 0.0
    if len(use) < 3 or not delays.tau.size:
        return GeometryFit(np.nan, np.nan, np.nan, span, used=use)
    per_event, w = _event_misfits(delays.tau, delays.pairs, mics, use)
    misfit = float(np.quantile(per_event, MISFIT_QUANTILE))
    best = float(np.sort(per_event)[min(MISFIT_BEST_K, len(per_event)) - 1])
    if len(use) - 1 <= _rank(mics[list(use)]):  # as many delays as a plane wave's unknowns: any delays fit
        misfit = best = np.nan
    wc = np.linalg.norm(w, axis=1) * c
    full3d = is_volume(mics[list(use)])
    if full3d and directions is not None:
        wc = np.where((wc > 1.0) & _off_direction(w, directions), np.nan, wc)   # NaN: no testimony
    mode, support = consensus(wc)
    lwc = np.log(wc[wc > 0])
    scatter = float(mad_std(lwc)) if lwc.size >= 3 else 0.0   # (fewer: no scatter to speak of)
    if not full3d:  # |w|·c ≤ 1 for any plane wave: the events above it, if many, say the size is too small;
        # they spread with the sources' elevations (cos el / scale): the sources nearest the plane tell the scale.
        # Only events that are plane waves on the declared geometry testify (a size declared too small scales
        # every delay, the fit stays exact): a direct path mixed with a reflection bends the delays and lifts
        # |w|·c too (robot seed 97's wall-mounted reference: 5 of 12 chirps at 1.2-1.6, each misfit 19-33 % of
        # the largest delay, where its 4 clean chirps fit within 2.5 % at 0.14-0.43)
        over = wc[(wc > 1.0) & (per_event <= max(MISFIT_FLOOR_S, MISFIT_FAIL * span))]
        top = supported_top(over)
        support = len(over) / len(wc) if np.isfinite(top) else 0.0
        mode = top if np.isfinite(top) else np.max(wc)   # no supported top: the largest is only a bound
        scatter = 0.0   # (a planar array's |w|·c spreads with the elevations, not with the noise)
    scale = 1.0 / float(mode) if mode > 0 else np.nan
    loo = {m: _misfit(delays.tau, delays.pairs, mics, tuple(u for u in use if u != m))[0]
           for m in use} if len(use) - 2 > _rank(mics[list(use)]) else {}  # the rest still over-determined
    moved = {m: _moved(delays.tau, delays.pairs, mics, use, m) for m in loo}
    swaps = {}
    for a, b in combinations(use, 2):
        p = mics.copy()
        p[[a, b]] = p[[b, a]]
        swaps[(a, b)] = _misfit(delays.tau, delays.pairs, p, use)[0]
    return GeometryFit(misfit, misfit / max(span, 1e-12), scale, span, use, support, loo, swaps, moved, scatter,
                       best)


def _off_direction(w, directions):
    """(K,) True where the plane wave ``w`` (K, 3) points more than DIRECTION_AGREE_DEG from ``directions`` (K, 3),
    the frontend's DOAs (w ∝ the direction to the source); False where either is unknown."""
    d = np.asarray(directions, float)
    norm = np.linalg.norm(w, axis=1) * np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.sum(w * d, axis=1) / norm
    return np.isfinite(cos) & (cos < np.cos(np.radians(DIRECTION_AGREE_DEG)))


def inverted_channels(delays, exclude=()):
    """Mics whose pair peaks are mostly negative: ``{mic: fraction}`` for those above INVERTED_FRACTION,
    judged against the pairs with the other (not excluded) mics over all events."""
    out = {}
    m = delays.energy.shape[1]
    for k in range(m):
        if k in exclude:
            continue
        sel = ((delays.pairs[:, 0] == k) | (delays.pairs[:, 1] == k)) & \
            ~np.isin(delays.pairs[:, 0], exclude) & ~np.isin(delays.pairs[:, 1], exclude)
        if not np.any(sel):
            continue
        frac = float(np.mean(delays.sign[:, sel] < 0))
        if frac > INVERTED_FRACTION:
            out[k] = frac
    return out


def channel_levels_db(delays):
    """(M,) each channel's energy in the chirps' direct path, in dB relative to the array's median channel."""
    e = np.median(delays.energy, axis=0)
    ref = np.median(e)
    with np.errstate(divide="ignore"):
        return 10 * np.log10(np.maximum(e, 0) / ref) if ref > 0 else np.full(len(e), -np.inf)


@dataclass(frozen=True)
class BoardSpeed:
    """:func:`board_speed`'s result: c (m/s) the board's own delays say, its std (m/s: the events' scatter, the
    mic positions' tolerance, the delays' residual bias), n the events that agree on it, n_events those used."""
    c: float
    std: float
    n: int
    n_events: int


def board_speed(delays, mics, c0, directions=None, exclude=()):
    """The speed of sound a 3-D board's own inter-mic delays measure: a plane wave's slowness ``|w| = 1 / c``
    against the declared geometry (metres), no odometry involved — the absolute scale that tells a wrong declared
    speed of sound from a mis-scaled odometry, which the arrivals against the odometry cannot (they fix c / the
    odometry's scale). None for a planar or linear board (its delays see ``cos(el) / c`` only) or too few events.

    The events used: those whose plane wave points within DIRECTION_AGREE_DEG of the frontend's DOA
    (``directions`` (K, 3), NaN rows unknown: kept), then the largest group agreeing on ``|w|`` within
    CONSENSUS_TOL (a reflection that bends one mic's delay scales ``|w|`` anywhere from 0.1 to 3). std: the
    group's robust scatter over √n, the declared positions' tolerance (BOARD_MIC_TOL_M over the board's RMS
    radius: a wrong size reads as a wrong c) and BOARD_BIAS (the gate's and a near source's curvature: exact
    plane and spherical waves, tests/test_board_speed.py)."""
    mics = np.asarray(mics, float)
    use = tuple(m for m in range(len(mics)) if m not in exclude)
    p = mics[list(use)]
    if len(use) < 4 or not is_volume(p) or not delays.tau.size:   # (nearly planar: its out-of-plane slowness
        return None                                                  # is too poorly measured)
    tau = delays.tau if delays.tau_flat is None else delays.tau_flat
    _, w = _event_misfits(tau, delays.pairs, mics, use)
    wc = np.linalg.norm(w, axis=1) * c0
    if directions is not None:
        wc = wc[~_off_direction(w, directions)]
    wc = wc[np.isfinite(wc) & (wc > 0)]
    lx = np.log(wc)
    group = _largest_group(lx, CONSENSUS_TOL)
    if group.size < BOARD_MIN_EVENTS or group.size < BOARD_SUPPORT * lx.size:
        return None
    radius = float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
    rel = np.sqrt(max(float(mad_std(group)), BOARD_SCATTER_FLOOR) ** 2 / group.size
                  + (BOARD_MIC_TOL_M / (radius * np.sqrt(len(use)))) ** 2 + BOARD_BIAS ** 2)
    c = float(c0 * np.exp(-np.median(group)))
    return BoardSpeed(c, c * rel, int(group.size), int(len(wc)))


# ----------------------------------------------------------------------------------------------- one array
def check_array(a, session, times=None, scores=None, threshold=8.0, n_events=N_EVENTS, clock_times=None):
    """Measure one array's channels (:class:`PairDelays`) and its clock against the emission times.

    a : the session's array dict (name, wav, mics); session : the in-memory session (chirp, events,
    speed_of_sound). times, scores : the chirps' detection times (s) and scores, if already known (the
    features' diagnostics); else detected here. clock_times : the detections the clock is measured on (default
    ``times``: a caller that keeps only some chirps for the delays still times the clock on every chirp).
    Returns a dict: delays (:class:`PairDelays` or None when no chirp was found), n_detected, clock_scale,
    clock_support, clock_times, fs."""
    t_emit = session["events"]["t_emit"].to_numpy(float)
    with ArrayAudio(a) as x:
        fs = x.fs
        template = chirp_template(session["chirp"], fs)
        band = chirp_band(session["chirp"], template, fs)
        if times is None:
            times, scores = detect_chirps(x, template, fs, band, t_emit, threshold)
        times, scores = np.asarray(times, float), np.asarray(scores, float)
        clock_times = times if clock_times is None else np.asarray(clock_times, float)
        scale, support = clock_scale(clock_times, t_emit)
        if not len(times):
            return {"delays": None, "n_detected": 0, "clock_scale": scale, "clock_support": support,
                    "clock_times": clock_times, "fs": fs}
        keep = np.sort(times[np.argsort(-scores)[:n_events]])
        delays = measure_delays(x, a["mics"], template, fs, band, keep, session["speed_of_sound"])
    return {"delays": delays, "n_detected": int(len(times)), "clock_scale": scale, "clock_support": support,
            "clock_times": clock_times, "fs": fs}
