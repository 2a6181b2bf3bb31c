"""Chirp detection: matched-filter envelope of a whole recording (block-wise) and robust peak picking."""
from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from calib.memo import SetupCache


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
    while q0 < n_valid:
        # the last block only as long as what is left needs (a 28 s recording at 48 kHz: 7 blocks of 2^18
        # samples, the seventh for 3 % of its outputs)
        nd_b = min(nd, _fast_length(n_valid - q0 + overlap))
        nfft, q1 = nd_b * dec, min(q0 + nd_b - overlap, n_valid)
        k0 = int(np.floor(band[0] * nfft / fs))
        k1 = min(int(np.ceil(band[1] * nfft / fs)) + 1, nfft // 2 + 1, k0 + nd_b)
        s_conj = _template_band(template, nfft, k0, k1)
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


_TEMPLATE_BANDS = SetupCache(16)  # a full-length block per rate, a shorter last one per recording


def _template_band(template, nfft, k0, k1):
    """Conjugate of the template's FFT (float32, length ``nfft``) on bins ``k0 .. k1 − 1``: the arrays of a
    session share the chirp and (at one rate) the block length, so it is computed once (small cache)."""
    t32 = np.ascontiguousarray(template, np.float32)
    return _TEMPLATE_BANDS.get((t32.tobytes(), nfft, k0, k1), lambda: np.conj(sfft.rfft(t32, nfft)[k0:k1]))


def _columns(x, a, b):
    """``x[:, a:b]`` with zeros for columns before 0 (those after the end are left out: the FFT pads)."""
    if a >= 0 or not isinstance(x, np.ndarray):
        return x[:, a:b]
    return np.concatenate([np.zeros((x.shape[0], -a), x.dtype), x[:, 0 : max(b, 0)]], axis=1)


def local_floor(env, block):
    """Robust local background of an envelope: per-block medians, the max over each block's neighbours.

    Reverberant tails raise the background after every chirp; a peak must stand out from this local
    level (and from the global median) to count as a detection.

    env : (N,). block : samples per block. Returns (N,).
    """
    n = len(env)
    nb = max(1, n // block)
    med = median_last(env[: nb * block].reshape(nb, -1)) if n >= block else np.array([median_last(env)])
    med = np.r_[med, med[-1]] if nb * block < n and n >= block else med  # the partial last block
    neigh = np.maximum(med, np.maximum(np.r_[med[1:], med[-1]], np.r_[med[0], med[:-1]]))
    level = np.maximum(neigh, median_last(env))  # per block: the max commutes with the repetition
    out = np.empty(n, level.dtype)  # sample k gets level[min(k // block, last)], written block-wise
    n_full = min(n // block, len(level))
    out[: n_full * block].reshape(n_full, block)[...] = level[:n_full, None]
    out[n_full * block :] = level[min(n_full, len(level) - 1)]
    return out


def median_last(a):
    """``np.median(a, axis=-1)`` of a NaN-free array, bit-identical and ~2–3× faster: one selection at the
    upper middle, the lower middle (even length) as the maximum of the part below it, where numpy's
    median runs a second selection. A long 1-D array (a recording's envelope) selects among the few
    values a sorted subsample brackets the middle with (:func:`_bracketed_middle`; ~4× faster again)."""
    n = a.shape[-1]
    h = n // 2
    if a.ndim == 1 and n >= BRACKET_MIN:
        middle = _bracketed_middle(a)
        if middle is not None:
            return middle if n % 2 else np.mean(np.stack(middle, axis=-1), axis=-1)
    part = np.partition(a, h, axis=-1)
    if n % 2:
        return part[..., h]
    return np.mean(np.stack([np.max(part[..., :h], axis=-1), part[..., h]], axis=-1), axis=-1)


BRACKET_MIN = 1 << 15   # 1-D arrays at least this long: median via a bracket from a subsample
BRACKET_SAMPLE = 4096   # about this many values in the subsample
BRACKET_SD = 5.0        # bracket half-width: this many binomial standard deviations of the middle's rank


def _bracketed_middle(a):
    """The value at rank ``n // 2`` of a 1-D array (odd length), or the values at ranks ``n//2 − 1`` and
    ``n//2`` (even), exactly: a sorted subsample gives values ``lo ≤ hi`` whose ranks bracket the middle
    with a margin of ``BRACKET_SD`` standard deviations; one count of the values below ``lo`` and a
    selection among the few in ``[lo, hi]`` give the exact order statistics. None when the bracket
    missed (then the caller selects over everything)."""
    n = len(a)
    h = n // 2
    sample = np.sort(a[:: max(1, n // BRACKET_SAMPLE)])
    s = len(sample)
    margin = int(BRACKET_SD * 0.5 * np.sqrt(s)) + 2
    lo, hi = sample[max(s // 2 - margin, 0)], sample[min(s // 2 + margin, s - 1)]
    below = int(np.count_nonzero(a < lo))
    inside = a[(a >= lo) & (a <= hi)]
    first = h - 1 if n % 2 == 0 else h  # the lowest rank needed
    if not below <= first or not h < below + len(inside):
        return None
    ranks = [first - below, h - below] if n % 2 == 0 else [h - below]
    vals = np.partition(inside, ranks)[ranks]
    return vals[0] if n % 2 else (vals[0], vals[1])


def pick_peaks(env, env_rate, min_separation, threshold=8.0, block_s=0.25):
    """Detections in a matched-filter envelope.

    Parameters
    ----------
    env : (N,) envelope sampled at ``env_rate`` (Hz).
    min_separation : s; of two peaks closer than this only the higher one is kept.
    threshold : a peak must exceed ``threshold`` × the local background.

    Returns
    -------
    idx : (D,) int, envelope samples of the detections (ascending).
    score : (D,) float, peak / local background.
    """
    floor = local_floor(env, max(1, int(block_s * env_rate)))
    dist = max(1, int(min_separation * env_rate))
    idx = _peaks_above(env, threshold * floor, dist)
    return idx, env[idx] / floor[idx]


PEAK_MARGIN = 64  # samples of context around the above-threshold runs in which local maxima are sought


def _peaks_above(env, height, distance):
    """``scipy.signal.find_peaks(env, height=height, distance=distance)[0]`` (the same peaks, without
    importing scipy.signal: ~0.4 s of every ``calib features``), found only in the stretches above
    ``height`` (a few per chirp) instead of among the millions of local maxima of the noise: the windows
    around those stretches are widened while the envelope stays flat at their edges, so a plateau's middle
    and its strictly lower neighbours are the ones :func:`local_maxima` sees."""
    above = np.flatnonzero(env >= height)
    if not above.size:
        return above
    cut = np.flatnonzero(np.diff(above) > 2 * PEAK_MARGIN)
    starts = np.maximum(above[np.r_[0, cut + 1]] - PEAK_MARGIN, 0)
    stops = np.minimum(above[np.r_[cut, len(above) - 1]] + PEAK_MARGIN + 1, len(env))
    found = []
    for a, b in zip(starts, stops):
        while a > 0 and env[a - 1] == env[a]:  # a plateau crossing the window's edge: take all of it
            a -= 1
        while b < len(env) and env[b] == env[b - 1]:
            b += 1
        p = local_maxima(env[a:b])
        p = p[env[a:b][p] >= height[a:b][p]]
        # a maximum at the window's edge is not one of the whole envelope's (its outer neighbour is unseen)
        found.append(a + p[((p > 0) | (a == 0)) & ((p < b - a - 1) | (b == len(env)))])
    peaks = np.unique(np.concatenate(found))
    return peaks[select_by_distance(peaks, env[peaks].astype(np.float64), distance)]


def local_maxima(x):
    """Indices of the local maxima of ``x`` (1-D) as ``scipy.signal.find_peaks`` defines them: a sample, or
    the middle (rounded down) of a run of equal samples, strictly above the samples on either side; the
    first and last samples never count."""
    change = np.flatnonzero(x[1:] != x[:-1]) + 1
    if len(change) < 2:
        return np.zeros(0, int)
    first, last = change[:-1], change[1:] - 1  # the runs with a neighbour on each side: [first, last]
    v = x[first]
    peak = (v > x[first - 1]) & (v > x[last + 1])
    return (first[peak] + last[peak]) // 2


def select_by_distance(peaks, priority, distance):
    """Mask of ``peaks`` (ascending indices) kept when of any two closer than ``distance`` samples only the
    one of higher ``priority`` stays, taken greedily from the highest (``find_peaks``'s ``distance``
    rule, ties broken as it breaks them)."""
    keep = np.ones(len(peaks), bool)
    gap = np.ceil(distance)
    for j in np.argsort(priority)[::-1]:
        if keep[j]:
            lo = np.searchsorted(peaks, peaks[j] - gap, side="right")  # peaks[lo:j] are within the gap
            hi = np.searchsorted(peaks, peaks[j] + gap, side="left")   # and so are peaks[j + 1:hi]
            keep[lo:j] = keep[j + 1 : hi] = False
    return keep


def refine_peak(y, k):
    """Parabolic sub-sample position of a peak of ``y`` at integer index(es) ``k`` (clipped at the ends)."""
    k = np.clip(np.asarray(k), 1, len(y) - 2)
    a, b, c = y[k - 1], y[k], y[k + 1]
    den = a - 2 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return k + np.clip(off, -0.5, 0.5)


def redetect(env, env_rate, times, half_window, threshold, block_s=0.25):
    """Look for chirps the global detection missed, near times where they must be.

    The association's clock line predicts when each missed event arrives; within that narrow window a
    weaker peak is unlikely to be noise (the maximum of ``2 · half_window · env_rate`` noise samples is ~3×
    the background), so a lower threshold is safe there. Reverberation lowers a chirp's score (its tail
    raises the local background) without making it any less a chirp.

    env : (N,) envelope at ``env_rate``. times : (K,) predicted arrival times (s). half_window : s.
    threshold : peak / local background needed. Returns idx (K,) int envelope samples (−1: nothing) and
    score (K,) (nan where nothing).
    """
    floor = local_floor(env, max(1, int(block_s * env_rate)))
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
        if env[q] >= threshold * floor[q]:
            idx[k], score[k] = q, env[q] / floor[q]
    return idx, score
