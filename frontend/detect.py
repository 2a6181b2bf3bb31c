"""Chirp detection: matched-filter envelope of a whole recording (block-wise) and robust peak picking."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.fft as sfft


BLOCK_SAMPLES = 1 << 18  # envelope block (FFT) length: ~5 s at 48 kHz, bounded memory for any duration
EDGE_GUARD = 0.25        # × template length discarded at each block edge, beyond the L − 1 of overlap-save


def matched_envelope(x, template, fs, band, block=BLOCK_SAMPLES):
    """Envelope of the matched filter (correlation with the template), summed over channels, decimated.

    Only the chirp's band carries signal, so the analytic correlation is formed in the frequency domain
    from the band's bins alone and inverse-transformed at a reduced rate (complex baseband). Its magnitude
    is the envelope: a chirp starting at sample n gives a peak at n.

    Computed block by block (overlap-save): each block of about ``block`` samples is read, transformed and
    dropped, so memory is bounded by one block whatever the recording's length. Each block's outputs
    exclude the ``L − 1`` lags whose correlation wraps around plus a guard of ``EDGE_GUARD × L`` samples at
    either end, where the band-limiting (a circular filter over the block) would see the wrapped part.

    Parameters
    ----------
    x : (M, N) recording: an ndarray or anything sliceable as ``x[:, a:b]`` with a ``shape``
        (:class:`calib.frontend.signals.ArrayAudio`; zeros outside ``0..N−1``).
    template : (L,) emitted chirp at ``fs``.
    band : (f_lo, f_hi) Hz.
    block : FFT length per block (samples; raised to fit the template).

    Returns
    -------
    env : (N_d,) float32 (the one array that grows with the recording), sum over channels of |matched
        filter| normalised by the template energy (≈ the amplitude of a clean chirp), sampled at ``fs / dec``.
    dec : int, decimation factor (env[k] is at sample k * dec).
    """
    m, n = x.shape
    n_t = len(template)
    bw = band[1] - band[0]
    dec = max(1, int(fs / (1.25 * bw)))
    guard = -(-int(EDGE_GUARD * n_t) // dec)  # in decimated samples
    overlap = -(-(n_t - 1) // dec) + 2 * guard  # decimated samples of a block that give no output
    nd = _fast_length(max(-(-block // dec), overlap + 64))
    scale = 2.0 / (float(np.dot(template, template)) * dec)  # × 1 / nd_b per block: the inverse FFT is unscaled
    n_valid = -(-n // dec)
    env = np.zeros(n_valid, np.float32)
    q0, buf = 0, None  # first decimated output of the next block, the inverse transform's input
    bands = {}   # the template's band per block length (all blocks but the last share one)
    while q0 < n_valid:
        # the last block only as long as what is left needs (a 28 s recording at 48 kHz: 7 blocks of 2^18
        # samples, the seventh for 3 % of its outputs)
        nd_b = min(nd, _fast_length(n_valid - q0 + overlap))
        nfft, q1 = nd_b * dec, min(q0 + nd_b - overlap, n_valid)
        k0 = int(np.floor(band[0] * nfft / fs))
        k1 = min(int(np.ceil(band[1] * nfft / fs)) + 1, nfft // 2 + 1, k0 + nd_b)
        if nfft not in bands:
            bands[nfft] = _template_band(template, nfft, k0, k1)
        s_conj = bands[nfft]
        buf = buf if buf is not None and len(buf) == nd_b else np.zeros(nd_b, np.complex64)
        s0 = (q0 - guard) * dec  # first input sample of the block
        seg = _columns(x, s0, s0 + nfft)
        for ch in range(m):  # one channel at a time
            spec = sfft.rfft(seg[ch], nfft)
            buf[: k1 - k0] = spec[k0:k1] * s_conj
            # unnormalised inverse (norm="forward"): its 1 / nd_b is a pass over the block (~25 % of the transform)
            # folded into the block's one scaling below
            env[q0:q1] += np.abs(sfft.ifft(buf, norm="forward")[guard : guard + q1 - q0])
        env[q0:q1] *= np.float32(scale / (m * nd_b))
        q0 = q1
    return env, dec


def _fast_length(n):
    """Smallest length ≥ n of the form 2^a, 3·2^a or 5·2^a: with the decimation factor it makes the block's
    real FFT a fast one (``next_fast_len`` alone gave e.g. 26244 × 10 = 2³·3⁸·5, ~40 % slower per sample)."""
    return min(k << max(0, int(np.ceil(np.log2(n / k)))) for k in (1, 3, 5))


def _template_band(template, nfft, k0, k1):
    """Conjugate of the template's FFT (float32, length ``nfft``) on bins ``k0 .. k1 − 1``."""
    return np.conj(sfft.rfft(np.ascontiguousarray(template, np.float32), nfft)[k0:k1])


def _columns(x, a, b):
    """``x[:, a:b]`` with zeros for columns before 0 (those after the end are left out: the FFT pads)."""
    if a >= 0 or not isinstance(x, np.ndarray):
        return x[:, a:b]
    return np.concatenate([np.zeros((x.shape[0], -a), x.dtype), x[:, 0 : max(b, 0)]], axis=1)


def block_levels(env, block, median=None):
    """Robust local background of an envelope, one level per block of ``block`` samples: per-block medians,
    the max over each block's neighbours, at least the global median. The last block is partial where
    ``block`` does not divide N: the levels cover the N samples.

    Reverberant tails raise the background after every chirp; a peak must stand out from this local
    level (and from the global median) to count as a detection. median : ``np.median(env)`` when known.
    """
    n = len(env)
    nb = max(1, n // block)
    med = np.median(env[: nb * block].reshape(nb, -1), axis=-1) if n >= block else np.array([np.median(env)])
    med = np.r_[med, med[-1]] if nb * block < n and n >= block else med  # the partial last block
    neigh = np.maximum(med, np.maximum(np.r_[med[1:], med[-1]], np.r_[med[0], med[:-1]]))
    return np.maximum(neigh, np.median(env) if median is None else median)


def local_floor_at(level, block, a, b):
    """Samples ``a .. b − 1`` of the per-sample floor of the block ``level``s (:func:`block_levels`):
    repeated, not gathered through int64 indices (20 bytes a sample: 0.6 GB for a 2-hour envelope)."""
    return np.repeat(level[a // block : -(-b // block)], block)[a % block : a % block + b - a]


PEAK_CHUNK = 1 << 20   # envelope samples compared with the detection threshold at a time


def _above(env, level, block, height):
    """Samples of ``env`` at or above ``height`` × their block's level (ascending), a chunk at a time."""
    out = []
    for a in range(0, len(env), PEAK_CHUNK):
        b = min(a + PEAK_CHUNK, len(env))
        out.append(np.flatnonzero(env[a:b] >= height * local_floor_at(level, block, a, b)) + a)
    return np.concatenate(out) if out else np.zeros(0, int)


def _segments(env, pos, dist):
    """[a, b) spans of ``env`` around the samples ``pos``: those closer than ``dist`` in one span, each span
    widened past any flat run at its ends by one differing sample (so a peak's plateau and its rise and fall
    lie inside: local maxima found in a span are the envelope's)."""
    if not len(pos):
        return []
    cut = np.flatnonzero(np.diff(pos) > dist)
    spans = []
    for a, b in zip(pos[np.r_[0, cut + 1]], pos[np.r_[cut, len(pos) - 1]] + 1):
        while a > 0 and env[a - 1] == env[a]:
            a -= 1
        while b < len(env) and env[b] == env[b - 1]:
            b += 1
        spans.append((max(a - 1, 0), min(b + 1, len(env))))
    return spans


BLOCK_S = 0.25   # s: the blocks of the local background (:func:`block_levels`) of the detections


class Background(NamedTuple):
    """An envelope's local background: ``levels`` (:func:`block_levels` in blocks of ``block`` samples) and
    the whole envelope's ``median`` (their floor)."""
    levels: np.ndarray
    block: int
    median: float


def background(env, env_rate, block_s=BLOCK_S):
    """:class:`Background` of ``env`` in blocks of ``block_s`` seconds. Computed once per envelope and shared
    by :func:`pick_peaks`, :func:`redetect` and the detection plot's summary (each a median over every
    sample: a tenth of the frontend on a hall)."""
    block = max(1, int(block_s * env_rate))
    median = float(np.median(env))
    return Background(block_levels(env, block, median), block, median)


def pick_peaks(env, env_rate, min_separation, threshold=8.0, block_s=BLOCK_S, levels=None):
    """Detections in a matched-filter envelope.

    Parameters
    ----------
    env : (N,) envelope sampled at ``env_rate`` (Hz).
    min_separation : s; of two peaks closer than this only the higher one is kept.
    threshold : a peak must exceed ``threshold`` × the local background (:func:`block_levels`).
    levels : :func:`background` of ``env`` when already computed.

    Returns
    -------
    idx : (D,) int, envelope samples of the detections (ascending).
    score : (D,) float, peak / local background.

    The peaks of :func:`find_peaks` (as ``scipy.signal.find_peaks(env, height=threshold × local_floor,
    distance)``), found only around the samples above the threshold (:func:`_segments`): memory bounded by
    the chirps, not the recording (find_peaks on a whole 2-hour envelope at 4.8 kHz holds ~0.8 GB of float64 copies and local maxima).
    """
    level, block, _ = background(env, env_rate, block_s) if levels is None else levels
    dist = max(1, int(min_separation * env_rate))
    found = [a + find_peaks(env[a:b], threshold * local_floor_at(level, block, a, b), dist)
             for a, b in _segments(env, _above(env, level, block, threshold), dist)]
    idx = np.concatenate(found) if found else np.zeros(0, int)
    return idx, env[idx] / level[idx // block]


def find_peaks(y, height, distance):
    """``scipy.signal.find_peaks(y, height=height, distance=distance)[0]``, the same peaks: local maxima (a flat
    top counts once, at its middle; not the ends of ``y``) at or above ``height`` ((N,) or a scalar), then of
    two closer than ``distance`` samples only the higher (the highest first). Here because importing
    scipy.signal (and the scipy.stats it pulls in) costs ~0.35 s of CPU, a fifth of `calib features` on a
    short session. y : (N,); returns (P,) int ascending."""
    y = np.asarray(y)
    n = len(y)
    if n < 3:
        return np.zeros(0, np.intp)
    dy = np.diff(y)
    change = np.flatnonzero(dy != 0)                    # y[k + 1] != y[k]
    rise = np.flatnonzero(dy[: n - 2] > 0) + 1          # y[i − 1] < y[i], 1 ≤ i ≤ n − 2
    nxt = np.searchsorted(change, rise)                 # the first change at or after i: the end of i's flat run
    has = nxt < len(change)
    rise, k = rise[has], change[nxt[has]]
    top = dy[k] < 0                                     # then a fall: a maximum over i .. k
    peaks = (rise[top] + k[top]) // 2
    peaks = peaks[y[peaks] >= np.broadcast_to(height, y.shape)[peaks]]
    return peaks[_select_by_distance(peaks, y[peaks].astype(np.float64), distance)]


def _select_by_distance(peaks, priority, distance):
    """(P,) bool: the peaks kept when, highest first, each removes the lower ones closer than ``distance``
    (scipy.signal's order, ties included: the same argsort). A loop over the candidates above the threshold
    only: a few per chirp."""
    keep = np.ones(len(peaks), bool)
    d = int(np.ceil(distance))
    for j in np.argsort(priority)[::-1]:
        if keep[j]:
            lo, hi = np.searchsorted(peaks, [peaks[j] - d + 1, peaks[j] + d])
            keep[lo:j] = False
            keep[j + 1 : hi] = False
    return keep


def refine_peak(y, k):
    """Parabolic sub-sample position of a peak of ``y`` at integer index(es) ``k`` (clipped at the ends)."""
    k = np.clip(np.asarray(k), 1, len(y) - 2)
    a, b, c = y[k - 1], y[k], y[k + 1]
    den = a - 2 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return k + np.clip(off, -0.5, 0.5)


def redetect(env, env_rate, times, half_window, threshold, block_s=BLOCK_S, levels=None):
    """Look for chirps the global detection missed, near times where they must be.

    The association's clock line predicts when each missed event arrives; within that narrow window a
    weaker peak is unlikely to be noise (the maximum of ``2 · half_window · env_rate`` noise samples is ~3×
    the background), so a lower threshold is safe there. Reverberation lowers a chirp's score (its tail
    raises the local background) without making it any less a chirp.

    env : (N,) envelope at ``env_rate``. times : (K,) predicted arrival times (s). half_window : s.
    threshold : peak / local background needed. levels : :func:`background` of ``env`` when already
    computed. Returns idx (K,) int envelope samples (−1: nothing) and score (K,) (nan where
    nothing).
    """
    level, block, _ = background(env, env_rate, block_s) if levels is None else levels   # q's floor: level[q // block]
    idx = np.full(len(times), -1)
    score = np.full(len(times), np.nan)
    h = max(1, int(round(half_window * env_rate)))
    for k, t in enumerate(np.asarray(times, float)):
        c = int(round(t * env_rate))
        lo, hi = max(1, c - h), min(len(env) - 1, c + h + 1)
        if hi - lo < 3:
            continue
        q = lo + int(np.argmax(env[lo:hi]))
        if q in (lo, hi - 1):  # the window's edge: the rising flank of something outside
            continue
        if env[q] >= threshold * level[q // block]:
            idx[k], score[k] = q, env[q] / level[q // block]
    return idx, score
