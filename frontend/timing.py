"""Sub-sample arrival times of the chirp at each microphone: band-limited GCC-PHAT against the emitted chirp.

For an event segment ``x_m`` of mic ``m`` (starting a little before the detection), the whitened,
band-limited cross-spectrum with the template ``s`` is ``C_m(f) = W(f) X_m S* / A_m(f)``, with ``W`` a
tapered window over the chirp's band and ``A_m`` the magnitude of ``X_m S*`` smoothed over ~500 Hz (a
"smoothed PHAT": full PHAT, ``A = |X S*|``, also whitens the fine structure of the reverberation, and its
two-sided inverse filter then smears reflection energy ahead of the direct path; on the simulator's rooms
it tripled the TDOA error and multiplied the DOA error by 5–10, docs/frontend.md). Its inverse transform
``r_m(τ)`` is the mic's impulse response as seen through the chirp: a sharp pulse at the direct path's lag
(the chirp's start), then reflections. Times are found in three steps:

1. the array's direct path: the earliest strong peak of the channel-averaged envelope ``Σ|r_m|`` near the
   detection (the strongest peak can be a reflection; a reflection never precedes the direct path);
2. per mic, the envelope peak within the lags the array's aperture allows around it;
3. per mic, the carrier peak of ``Re(e^{-jφ} r_m(τ))`` nearest that envelope peak (half a carrier period at
   most, so no cycle slips), refined by Newton steps on the exact band-limited correlation.

``φ`` is the phase of the received chirp relative to the template at the envelope peak. It is 0 for an
exact template on a perfect clock, π for a speaker wired with inverted polarity, ±π/2 for a sine/cosine
mix-up, and a clock drift ``δ`` rotates it too (an LFM stretched in time is a slightly different LFM;
about 0.4 rad per 1e-4 for a 0.5 s, 500–4000 Hz sweep). So it is estimated per array from all its events
and mics (:func:`estimate_phase`); the carrier then refines the envelope's timing, event to event, without
cycle slips, and the timing follows the envelope's drift bias, which is linear in ``δ``.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.fft as sfft
from scipy.ndimage import maximum_filter1d, uniform_filter1d

from calib.robust import mad_std

from .signals import band_weights, fourier_resample


def spectra_setup(template, fs, band, seg_len, whiten_hz=500.0):
    """Fixed FFT quantities for one array: FFT size, in-band bins and weights, template spectrum.

    seg_len : samples per event segment; lags up to ``seg_len − len(template)`` are free of circular
    wrap-around. whiten_hz : width (Hz) of the smoothing of the magnitude that
    whitens the cross-spectrum; 0 = plain matched filter. Returns a dict (nfft, kb (Fb,), freqs (Fb,),
    weights (Fb,), tmpl_conj (Fb,), fs, seg_len, whiten_bins).
    """
    # the lags we use keep the whole template inside the segment; 2·3·5-smooth (real=True): pocketfft's real
    # transform does factors 7 and 11 in a slow generic pass (29040 = 2⁴·3·5·11² took 25 % longer than
    # 29160 = 2³·3⁶·5)
    nfft = sfft.next_fast_len(seg_len, real=True)
    freqs_all = sfft.rfftfreq(nfft, 1 / fs)
    w = band_weights(freqs_all, band)
    kb = np.flatnonzero(w > 0)
    tmpl = sfft.rfft(template, nfft)[kb]
    return {"nfft": nfft, "kb": kb, "freqs": freqs_all[kb], "weights": w[kb], "tmpl_conj": np.conj(tmpl),
            "tmpl_conj64": np.conj(tmpl).astype(np.complex64),
            "fs": fs, "seg_len": seg_len, "whiten_bins": int(round(whiten_hz * nfft / fs))}


def shared_setup(template, fs, band, seg_len, whiten_hz=500.0):
    """:func:`spectra_setup`, one dict for every array with the same template, rate, band and segment length
    (the boards of one kind in a session): the pulses, phasor tables and Doppler banks it caches as the timing
    stage runs (``_pulse_cache``, ``_offset_tables``, ``_stretch_banks``) are then computed once, not per
    array (a 48 kHz hall of six tetrahedra: ~0.1 s). Read-only apart from those caches, whose values depend
    only on the key (threads may fill one twice: the same values)."""
    t = np.ascontiguousarray(template, float)
    return _shared_setup(t.tobytes(), int(fs), (float(band[0]), float(band[1])), int(seg_len), float(whiten_hz))


@lru_cache(maxsize=8)
def _shared_setup(template_bytes, fs, band, seg_len, whiten_hz):
    return spectra_setup(np.frombuffer(template_bytes, float), fs, band, seg_len, whiten_hz)


# a float32 spectrum floor: the smallest normal float32 (a recording of denormal samples would divide by zero)
F32_FLOOR = float(np.finfo(np.float32).tiny)


def segment_spectra(x, starts, setup, plain=False, workers=-1):
    """Whitened, band-limited cross-spectra of event segments with the template (a GCC against the chirp).

    x : (M, N) recording. starts : (J,) int, first sample of each segment (may run off either end of the
    recording; the missing part is zero). Returns C : (J, M, Fb) complex64, scaled so that a perfect
    single-path match has a correlation peak of 1 (single precision, as the segment's FFT: the work per
    event is elementwise over the band and memory-bound; double precision doubled its traffic for rounding
    ~1e-7 of the peak, which moves a timing by ~1e-11 s). plain : also return the band-limited matched filter
    without whitening (same scaling), whose response is causal: the whitening filter is two-sided and puts
    reflection energy ahead of the direct path, where the onset search would take it for an arrival.
    workers : threads of the segments' FFT (``scipy.fft``; −1 = one per core). 1 when the caller already
    runs one array per core: a second FFT thread per array then only competes (~5 % more time).
    """
    spec = _band_spectra(x, starts, setup, workers)  # (J, M, Fb) complex64
    c = spec * setup["tmpl_conj64"]  # complex64 throughout (see above)
    pow_spec = _power(spec)  # |X|², float32
    c_plain = None
    w = setup["weights"] / setup["weights"].sum()
    w32 = w.astype(np.float32)
    if plain:
        p = np.sum(np.abs(setup["tmpl_conj"]) ** 2 * w)  # a single path of unit gain peaks at 1
        scale = 1.0 / np.maximum(p * np.sqrt(np.mean(pow_spec, axis=-1, keepdims=True, dtype=np.float64)
                                             / np.mean(np.abs(setup["tmpl_conj"]) ** 2)), F32_FLOOR)
        c_plain = c * (w32 * scale.astype(np.float32))
    if setup["whiten_bins"]:
        # divide by the locally smoothed magnitude: removes the spectral colour of speaker, room and noise
        # (as PHAT does) but not the fine structure of the reverberation, whose full whitening would smear
        # energy ahead of the direct path (a zero-phase inverse filter is two-sided)
        pow_spec *= np.abs(setup["tmpl_conj64"]) ** 2  # |c|² = |X|² |S|²
        p = uniform_filter1d(pow_spec, setup["whiten_bins"], axis=-1, mode="nearest")
        np.maximum(p, np.float32(max(1e-30 * float(p.max(initial=0.0)), F32_FLOOR)), out=p)
        np.sqrt(p, out=p)
        c *= np.divide(w32, p, out=p)
    else:
        c *= w32 / np.sqrt(np.maximum(np.mean(_power(c), axis=-1, keepdims=True), np.finfo(np.float32).tiny))
    return (c, c_plain) if plain else c


def _band_spectra(x, starts, setup, workers=-1):
    """The band's bins (J, M, Fb) complex64 of each event segment's FFT (:func:`segment_spectra`), a few events
    at a time (:data:`SEGMENT_BATCH_BYTES`): their zero-padded segments and full spectra stay small and reuse
    their memory, where all J at once wrote two arrays of ~10 MB per chunk into freshly mapped pages, whose
    faults were half of the stage's CPU (a 48 kHz hall). Each row's transform is the same as in one batch."""
    m, n = x.shape
    seg_len, nfft, kb = setup["seg_len"], setup["nfft"], setup["kb"]
    k0, k1 = int(kb[0]), int(kb[-1]) + 1
    band = slice(k0, k1) if k1 - k0 == len(kb) else kb   # contiguous (always, from band weights)
    starts = np.asarray(starts, int)
    out = np.empty((len(starts), m, len(kb)), np.complex64)
    per = max(1, int(SEGMENT_BATCH_BYTES // (4 * m * nfft)))
    seg = np.empty((min(per, max(len(starts), 1)), m, nfft), np.float32)  # zero-padded: no padded copy in rfft
    fill = getattr(x, "fill_segment", None)  # signals.ArrayAudio: read straight into the segment array
    for j0 in range(0, len(starts), per):
        batch = starts[j0 : j0 + per]
        for i, s0 in enumerate(batch):
            a = max(s0, 0)
            b = max(min(s0 + seg_len, n), a)   # [a, b): the samples inside the recording (none: a = b)
            seg[i, :, : a - s0] = 0
            seg[i, :, b - s0 :] = 0
            if b > a and fill is not None:
                fill(seg[i, :, a - s0 : b - s0], a)
            elif b > a:
                seg[i, :, a - s0 : b - s0] = x[:, a:b]  # x may be a transposed (sample-major) view
        out[j0 : j0 + len(batch)] = sfft.rfft(seg[: len(batch)], axis=-1, workers=workers)[..., band]
    return out


SEGMENT_BATCH_BYTES = 3e6   # event segments transformed at a time (float32 bytes; each FFT's output as much again)


def stretch_bank(template, setup, stretches):
    """Factors ``S_ε* / S*`` over the band (n, Fb) complex64 that turn :func:`segment_spectra`'s cross-spectra
    with the template into those with the template received stretched by ``1 + ε`` about its start (a
    source moving during the sweep, ε = ṙ/c), for each ε of ``stretches``, realised exactly as ``k / pad``
    (the stretched template's spectrum, :func:`_stretched_spectra`). The whitening divides by the smoothed magnitude,
    which a stretch of ~1e-3 leaves unchanged, so multiplying by the factor is the whitened GCC against the
    stretched template. Returns (factors, stretches realised (n,))."""
    banks = setup.setdefault("_stretch_banks", {})   # (a shared setup outlives a session: a few kept)
    key = (len(template), tuple(np.round(np.asarray(stretches, float), 12)))
    bank = banks.get(key)
    if bank is None:   # (the stretched spectra themselves are shared by the session's arrays)
        for old in list(banks)[: max(0, len(banks) - KEPT_BANKS + 1)]:   # oldest first (threads: no iterator)
            banks.pop(old, None)
        bank = banks[key] = _stretch_bank(template, setup, stretches)
    return bank


KEPT_BANKS = 4   # Doppler banks kept per setup (each rows × band bins complex64, ~0.5-1.5 MB)


def _stretch_bank(template, setup, stretches):
    n, nfft, kb = len(template), setup["nfft"], setup["kb"]
    step = np.min(np.abs(np.diff(np.sort(stretches)))) if len(stretches) > 1 else 1e-3
    # ε is realised as k / pad: within a quarter step of the grid
    pad = sfft.next_fast_len(max(2 * n, int(np.ceil(4.0 / max(step, 1e-9)))))
    ks = tuple(int(round(d * pad)) for d in stretches)
    ref = np.conj(setup["tmpl_conj"])
    ok = np.abs(ref) > 1e-6 * np.max(np.abs(ref))
    k0 = int(kb[0])
    spec = _stretched_spectra(np.asarray(template, float).tobytes(), nfft, k0, int(kb[-1]) + 1 - k0, pad, ks)[:, kb - k0]
    out = np.where(ok, np.conj(spec) / np.where(ok, np.conj(ref), 1.0), 0.0)
    return out.astype(np.complex64), np.asarray(ks) / pad


@lru_cache(maxsize=4)
def _stretched_spectra(template_bytes, nfft, k0, n_bins, pad, ks):
    """Bins ``k0 .. k0 + n_bins − 1`` of the ``nfft``-point DFT of the template (float64 bytes) received stretched
    by ``1 + k / pad`` about its start, for each k of ``ks``: (len(ks), n_bins) complex. The band-limited template
    stretched by 1 + ε and sampled has the spectrum ``(1 + ε) S((1 + ε) f)`` (S its DTFT; its band lies far
    below the Nyquist frequency, so nothing aliases), evaluated at the bins alone by a chirp z-transform of
    the template (FFTs of ``n + n_bins`` points, a 2·3·5-smooth size). It equals resampling the template
    zero-padded to ``pad`` samples to ``pad + k`` (the former way) and transforming, to ~1e-12 of the peak at
    48 kHz (1e-9 at 16 kHz; 95-97 % of a bank's complex64 factors bitwise the same), at 2-3x less CPU: those
    resamplings ran at lengths ``pad + k`` with large prime factors. The same for every array of a rate
    whose segments share ``nfft`` (the session's boards of one kind)."""
    s = np.frombuffer(template_bytes, float)
    n = len(s)
    size = sfft.next_fast_len(n + n_bins - 1)
    i, b = np.arange(n, dtype=np.int64), np.arange(n_bins, dtype=np.int64)
    m = np.arange(-(n - 1), n_bins, dtype=np.int64)
    out = np.empty((len(ks), n_bins), complex)
    for row, k in enumerate(ks):
        # bin (k0 + b) at the stretched rate: e^{−j2π φ (k0 + b) i}, φ = (pad + k) / (pad nfft); with
        # b i = (b² + i² − (b − i)²) / 2 a convolution (Bluestein). Phases in exact integer cycles of 2 pad nfft.
        num, den = pad + k, 2 * pad * nfft
        kernel = np.zeros(size, complex)
        kernel[np.mod(m, size)] = _cis(m * m, num, den, 1.0)
        y = sfft.ifft(sfft.fft(s * _cis(2 * k0 * i + i * i, num, den, -1.0), size) * sfft.fft(kernel),
                      overwrite_x=True)
        out[row] = (num / pad) * _cis(b * b, num, den, -1.0) * y[:n_bins]
    return out


def _cis(q, num, den, sign):
    """e^{± j2π q num / den} for integer arrays ``q`` (reduced modulo ``den`` first: no int64 overflow)."""
    return np.exp(sign * 2j * np.pi * (np.mod(np.mod(q, den) * num, den) / den))


def matched_stretch(c_plain, setup, bank, lo, hi, snr_factor=6.0, min_ratio=0.05, sidelobe_margin=2.0, stretches=None,
                    bound=None, coarse=1):
    """Index (J,) of the row of ``bank`` (:func:`stretch_bank`) whose stretched template gives each event's
    DIRECT PATH its highest peak: the Doppler filter that compresses the sweep of a moving source into one
    pulse (unstretched, it spreads over 2|ε|T, ~1 ms at 0.5 m/s, and its peak then moves with the path's
    curvature, reflections and noise by hundreds of µs). The direct path is the onset of the plain matched
    filter on lags lo..hi (:func:`direct_path_lag`, settings as :func:`locate`), not the strongest peak: a
    reflection has its own Doppler, and behind a directional speaker it is often the stronger.
    c_plain : (J, M, Fb) plain spectra (:func:`segment_spectra`). stretches : the bank's ε (n,) and bound :
    (J,) the largest |ε| each event can have (|ṙ| ≤ |v|: the source's speed); None: any row. Every
    ``coarse``-th row first, then the rows around each event's best (the peak falls smoothly off its row).
    Returns (rows (J,), (J, hi − lo) the mic-averaged plain envelope of each event with its row: the one
    :func:`locate` searches next, given as its ``onset_env`` instead of computed again; or None)."""
    n, J = len(bank), c_plain.shape[0]
    allowed = np.ones((n, J), bool) if bound is None else np.abs(np.asarray(stretches))[:, None] <= bound[None, :]
    peak = np.full((n, J), -np.inf)
    best = {"row": np.full(J, n), "env": np.zeros((J, hi - lo), np.float32)}   # row n: none yet
    ctx = (setup, lo, hi, pulse_envelope(setup, hi - lo, plain=True), pulse_near(setup, hi - lo, 2, plain=True),
           (snr_factor, min_ratio, sidelobe_margin), best)
    for i in range(0, n, coarse):
        _direct_peaks(c_plain, bank, i, allowed[i], peak, ctx)
    top = np.argmax(peak, axis=0)
    for i in range(n):
        near = allowed[i] & (np.abs(top - i) < coarse) & ~np.isfinite(peak[i])
        _direct_peaks(c_plain, bank, i, near, peak, ctx)
    rows = np.argmax(peak, axis=0)
    return rows, (best["env"] if np.array_equal(rows, best["row"]) else None)   # (None: a NaN peak somewhere)


def _direct_peaks(c_plain, bank, i, which, peak, ctx):
    """peak[i, which] = the direct path's height in the plain envelope with bank row i (in place); the envelope
    kept (``ctx``'s last: row and envelope per event) where row i is the event's best so far, ties to the lower
    row (as ``argmax`` over the rows)."""
    if not np.any(which):
        return
    setup, lo, hi, pulse, near, kw, best = ctx
    env = lag_grid(c_plain if np.all(which) else c_plain[which], setup, lo, hi, factor=bank[i],
                   magnitude=True).mean(axis=1)
    dp = direct_path_lag(env, pulse, *kw, near=near)[0]
    idx = np.flatnonzero(which)
    peak[i, idx] = val = env[np.arange(len(dp)), dp]
    old = np.where(best["row"][idx] < len(peak), peak[np.minimum(best["row"][idx], len(peak) - 1), idx], -np.inf)
    better = (val > old) | ((val == old) & (i < best["row"][idx]))
    best["row"][idx[better]] = i
    best["env"][idx[better]] = env[better]


def _power(z):
    """``|z|²`` of a complex array without the square root of ``np.abs``."""
    return z.real * z.real + z.imag * z.imag


@lru_cache(maxsize=32)
def _lag_plan(nfft, k0, n_q, n_t, lo, step):
    """Bluestein plan of :func:`lag_grid` in single precision (its set-up costs about as much as a
    transform, so it is reused across calls): with ``α = 2π step / nfft``, ``q t = (q² + t² − (t − q)²) / 2``
    turns ``Σ_q d_q e^{j2π q (lo + step t) / nfft}`` into a convolution with the chirp ``e^{−jα k² / 2}``.
    Returns (FFT length, pre-chirp (n_q,), kernel spectrum, post-chirp (n_t,) with the band's first bin
    ``k0`` put back), complex64; the phases are reduced modulo a cycle in float64 first. The kernel carries
    the inverse transform's ``1 / n`` (that transform then skips its scaling pass)."""
    n_fft = sfft.next_fast_len(n_q + n_t - 1, real=True)  # 2·3·5-smooth: ~10 % faster than with 7s and 11s
    q, t = np.arange(n_q), np.arange(n_t)
    k = np.arange(-(n_q - 1), n_t)

    def cis(cycles):  # e^{j2π cycles}, reduced to [0, 1) cycles while still exact in float64
        return np.exp(2j * np.pi * np.mod(cycles, 1.0)).astype(np.complex64)

    half = 0.5 * step / nfft
    pre = cis(q * (lo / nfft) + half * q * q)
    kernel = sfft.fft(cis(-half * k * k), n_fft) / np.float32(n_fft)  # the inverse FFT's 1 / n, once here
    post = cis(half * t * t + k0 * (lo + step * t) / nfft)
    return n_fft, pre, kernel, post


def lag_grid(c, setup, lo, hi, step=1.0, factor=None, magnitude=False):
    """Analytic correlation on the native lag grid: (J, M, hi − lo) complex64 for lag samples lo..hi-1
    (for peak search and gating; precise values come from :func:`newton_peak`). ``step`` < 1: ``(hi − lo) /
    step`` lags ``lo, lo + step, ...`` instead (a finer grid). factor : (Fb,) the spectra's weighting, applied
    here (``lag_grid(c * factor)``, no product array of its own). magnitude : return ``|r|`` (float32) instead.

    ``r[n] = Σ_k c_k e^{j2πkn/nfft}`` over the band's bins only, evaluated at the wanted lags alone by a
    chirp z-transform (FFTs of about Fb + (hi − lo) points instead of a full-length inverse FFT per mic),
    in single precision (the result is complex64 anyway; its rounding, ~1e-6 of the peak, is far below
    any noise floor).
    """
    nfft, kb = setup["nfft"], setup["kb"]
    k0, n_q, n_t = int(kb[0]), int(kb[-1] - kb[0] + 1), int(round((hi - lo) / step))
    n_fft, pre, kernel, post = _lag_plan(nfft, k0, n_q, n_t, float(lo), float(step))
    d = np.zeros(c.shape[:-1] + (n_fft,), np.complex64)
    cast = "same_kind" if c.dtype == np.complex64 else "unsafe"
    if len(kb) == n_q:  # contiguous band (always, from band weights): a slice, no scatter
        if factor is not None:   # (c × factor) × pre, the products rounded as with c × factor given
            np.multiply(c, factor, out=d[..., :n_q], casting=cast)
            d[..., :n_q] *= pre
        else:
            np.multiply(c, pre, out=d[..., :n_q], casting=cast)
    else:
        d[..., kb - k0] = (c if factor is None else c * factor) * pre[kb - k0]
    y = sfft.fft(d, axis=-1, overwrite_x=True)
    y *= kernel
    y = sfft.ifft(y, axis=-1, overwrite_x=True, norm="forward")  # unscaled: 1 / n is in the kernel
    r = y[..., n_q - 1 : n_q - 1 + n_t]
    if magnitude:   # (the product in place: y is this call's own)
        return np.abs(np.multiply(r, post, out=r))
    return r * post


def cis_powers(tau, f0, df, n):
    """``e^{j2π (f_0 + k Δf) τ}`` for k = 0 .. n − 1: (...,) lags (s) → (..., n) complex."""
    tau = np.asarray(tau, float)
    return np.exp(2j * np.pi * tau[..., None] * (f0 + df * np.arange(n)))


def cis_tables(tau, f0, df, b, n_a):
    """The inner and outer phasor tables of a uniform band folded into (A, B) blocks, ``f = f_0 + (aB + b')Δf``:
    ``cis_powers(tau, 0, Δf, B)`` and ``cis_powers(tau, f_0, BΔf, A)``. Returns ((..., B), (..., A))."""
    return cis_powers(tau, 0.0, df, b), cis_powers(tau, f0, df * b, n_a)


def phasors(freqs, tau, dtype=np.complex128):
    """``exp(j 2π f τ)`` for every f: (...,) lags (s) → (..., F) complex.

    The band's frequencies are uniformly spaced, ``f_k = f_0 + k Δf``; with ``k = a B + b`` (B ≈ √F) the
    phasor factors into ``e^{j2π(f_0 + aBΔf)τ} · e^{j2πbΔfτ}``: two tables of ~√F phasors
    (:func:`cis_powers`) and one vectorised complex multiply per element (2.3x faster than a cumulative
    product along the whole band, whose error would grow with F). dtype : of the result (np.complex64:
    the two tables in double precision, only their products rounded to single).
    """
    tau = np.asarray(tau, float)
    n_f = len(freqs)
    df = np.diff(freqs)
    if n_f < 3 or np.ptp(df) > 1e-9 * abs(df[0]):
        return np.exp(2j * np.pi * freqs * tau[..., None]).astype(dtype, copy=False)
    b = int(np.ceil(np.sqrt(n_f)))
    n_a = -(-n_f // b)
    inner, outer = cis_tables(tau, freqs[0], df[0], b, n_a)  # (..., B), (..., A)
    out = np.empty(tau.shape + (n_f,), dtype)
    full = (n_a - 1) * b
    np.multiply(outer[..., :-1, None], inner[..., None, :], out=out[..., :full].reshape(tau.shape + (n_a - 1, b)))
    out[..., full:] = outer[..., -1:] * inner[..., : n_f - full]
    return out


class BandSums:
    """``Σ_f a_f c_f e^{j2πfτ}`` of fixed spectra at changing lags without forming the (…, F) phasors.

    c : (..., F) spectra; factors : S weightings ``a_f`` (scalars or (F,)), giving S sums per lag. With uniformly spaced frequencies the
    band is folded into (A, B) blocks, ``f = f_0 + (aB + b)Δf``: a sum over ``b`` against ``B`` inner
    phasors, then over ``a`` against ``A`` outer ones (one multiply-add per element, as an einsum with
    the phasors, but no phasor array written and read back: ~2x faster).
    """

    def __init__(self, c, freqs, factors=(1.0,)):
        self.freqs = freqs
        n_f = len(freqs)
        df = np.diff(freqs)
        self.uniform = n_f >= 3 and np.ptp(df) <= 1e-9 * abs(df[0])
        self.b = int(np.ceil(np.sqrt(n_f))) if self.uniform else n_f
        self.n_a = -(-n_f // self.b)
        self.df = df[0] if self.uniform else 0.0
        cp = np.zeros((len(factors),) + c.shape[:-1] + (self.n_a * self.b,), np.result_type(c, np.complex64))
        for k, fac in enumerate(factors):  # written in place: no stacked or padded copies
            np.multiply(c, fac, out=cp[k, ..., :n_f])
        self.cs = cp if not self.uniform else cp.reshape(cp.shape[:-1] + (self.n_a, self.b))

    def __call__(self, tau):
        """tau : (...) lags (s), broadcastable with the spectra's middle axes → (S, ...) complex."""
        tau = np.asarray(tau, float)
        if not self.uniform:
            return np.einsum("s...f,...f->s...", self.cs, phasors(self.freqs, tau))
        inner, outer = cis_tables(tau, self.freqs[0], self.df, self.b, self.n_a)            # (..., B), (..., A)
        y = np.einsum("s...ab,...b->s...a", self.cs, inner)                                  # (S, ..., A)
        return np.einsum("s...a,...a->s...", y, outer)


class BandMoments:
    """``Σ_f c_f ω^k e^{jωτ}`` (ω = 2πf) for k = 0, 1, 2 at changing lags, reading the spectra once per
    call and never copying them (what Newton steps on the correlation need: value, slope, curvature).

    With uniformly spaced frequencies ``f = f_0 + (aB + b)Δf`` the band folds into (A, B) blocks
    (a view of ``c``; the last, partial block apart) and ``ω = Ω_a + ω_b``: one pass over ``c``
    against the ``B`` inner phasors times ``ω_b^k`` gives ``Y_k[a]``, and ``Σ_a`` of the outer phasors
    times ``Y_0``, ``Ω_a Y_0 + Y_1``, ``Ω_a² Y_0 + 2 Ω_a Y_1 + Y_2`` gives the three moments (the same
    sums as :class:`BandSums` with the factors ``1, ω, ω²``, up to rounding).
    """

    def __init__(self, c, freqs):
        self.c, self.freqs = c, freqs
        n_f = len(freqs)
        df = np.diff(freqs)
        self.uniform = n_f >= 3 and np.ptp(df) <= 1e-9 * abs(df[0])
        if not self.uniform:
            w = 2 * np.pi * freqs
            self._sums = BandSums(c, freqs, (1.0, w, w * w))
            return
        self.df, self.b = df[0], int(np.ceil(np.sqrt(n_f)))
        self.n_a = -(-n_f // self.b)
        self.full = (self.n_a - 1) * self.b
        self.head = c[..., : self.full].reshape(c.shape[:-1] + (self.n_a - 1, self.b))
        self.tail = c[..., self.full :]

    def __call__(self, tau, orders=3):
        """tau : (...) lags (s), broadcastable with the spectra's middle axes → (orders, ...) complex:
        the moments k = 0 .. orders − 1 (orders ≤ 3; 1 = the correlation alone, a third of the work)."""
        tau = np.asarray(tau, float)
        if not self.uniform:
            return self._sums(tau)[:orders]
        om = 2 * np.pi * self.df * np.arange(self.b)
        big = 2 * np.pi * (self.freqs[0] + self.df * self.b * np.arange(self.n_a))         # Ω_a
        inner, outer = cis_tables(tau, self.freqs[0], self.df, self.b, self.n_a)            # (..., B), (..., A)
        ik = (inner[..., None, :] * np.stack([np.ones_like(om), om, om * om][:orders])).astype(self.c.dtype)
        y = np.empty(np.broadcast_shapes(self.c.shape[:-1], tau.shape) + (orders, self.n_a), complex)
        y[..., :-1] = np.matmul(ik, np.swapaxes(self.head, -1, -2))                        # (..., K, A − 1)
        y[..., -1] = np.einsum("...b,...kb->...k", self.tail, ik[..., : self.tail.shape[-1]])
        y *= outer[..., None, :]
        y0 = y[..., 0, :]
        out = [y0.sum(-1)]
        if orders > 1:
            out.append((big * y0).sum(-1) + y[..., 1, :].sum(-1))
        if orders > 2:
            out.append((big * big * y0).sum(-1) + 2 * (big * y[..., 1, :]).sum(-1) + y[..., 2, :].sum(-1))
        return np.stack(out)


KERNEL_TOL = 1e-8  # GridMoments' kernel: its truncation and its leakage each below this × the nearby peak (rel.)


class GridMoments:
    """:class:`BandMoments` from samples of the correlation on the native lag grid, ``r[n] = r((r_lo + n) / fs)``
    (:func:`lag_grid`): each moment from the ``2G`` samples nearest the lag through a short band-pass
    interpolation kernel instead of a sum over the band's F bins (at 48 kHz, 30 taps against ~5800 bins).

    The correlation is exactly band-limited to the band's bins, a ``B``-wide band within a sampling rate
    of ``fs``, so it is its samples interpolated by any kernel that passes the band and stops its aliases:
    ``h(v) = e^{jav} sinc(v) e^{−v²/2σ²}`` (v in samples, ``a`` the band's centre in rad / sample). The
    Gaussian's spectral width ``1/(2πσ)`` fits in the margin ``d = ½ − B / (2 fs)`` between the band's
    edge and the sinc's cut-off, and its truncation at ``±G`` stays below :data:`KERNEL_TOL`; ``h'`` and
    ``h''`` give the slope and curvature. The values match the band sums to ~1e-7 of the nearby peak (the
    samples are single precision), which moves a timing by ~1e-11 s.

    r : (..., T) complex samples, or (T,): one correlation evaluated at lags of any shape; r_lo : lag of
    ``r[..., 0]`` (samples); setup : :func:`spectra_setup`'s dict. :meth:`covers` says whether the samples
    reach far enough.
    """

    def __init__(self, r, r_lo, setup, tol=KERNEL_TOL):
        fs, freqs = setup["fs"], setup["freqs"]
        self.r, self.fs = r, fs
        self.r_lo = float(r_lo)
        self.a = np.pi * (freqs[0] + freqs[-1]) / fs
        margin = 0.5 - (freqs[-1] - freqs[0]) / (2 * fs)
        k = np.sqrt(2 * np.log(1 / tol))
        self.sigma = k / (2 * np.pi * max(margin, 1e-3))
        self.g = int(np.ceil(k * self.sigma))

    def _taps(self, tau):
        u = np.asarray(tau, float) * self.fs - self.r_lo
        n0 = np.floor(u).astype(int)
        return u, n0[..., None] + np.arange(1 - self.g, self.g + 1)

    def covers(self, tau, first=0, slack=0):
        """True if the taps of every lag within ``slack`` samples of ``tau`` lie within the samples, from
        index ``first`` on (one, or one per row of ``r``'s first axis: its samples before are not computed)."""
        _, n = self._taps(tau)
        first = np.asarray(first).reshape(np.shape(first) + (1,) * (n.ndim - 1 - np.ndim(first)))
        return bool(np.all(n[..., 0] - slack >= first) and np.all(n[..., -1] + slack < self.r.shape[-1]))

    def __call__(self, tau, orders=3):
        """Like :meth:`BandMoments.__call__`: tau (...) lags (s) → (orders, ...) complex, ``Σ c ω^k e^{jωτ}``."""
        u, n = self._taps(tau)
        x = self.r[n] if self.r.ndim == 1 else np.take_along_axis(self.r, n, axis=-1)   # 1-D: shared by every lag
        h = _interp_kernel(u[..., None] - n, self.a, self.sigma, orders)
        out = [np.sum(x * h[0], axis=-1)]
        if orders > 1:  # r' = j Σ c ω e^{jωτ}, r'' = −Σ c ω² e^{jωτ}; per sample → per second
            out.append(-1j * self.fs * np.sum(x * h[1], axis=-1))
        if orders > 2:
            out.append(-self.fs**2 * np.sum(x * h[2], axis=-1))
        return np.stack(out)


SINC_SERIES = 1e-3  # |v| below this: sinc and its derivatives from their Taylor series (the quotients cancel)


def _interp_kernel(v, a, sigma, orders):
    """:class:`GridMoments`' kernel ``h(v) = e^{jav} sinc(v) e^{−v²/2σ²}`` and its first ``orders − 1``
    derivatives at offsets v (samples)."""
    pv = np.pi * v
    small = np.abs(v) < SINC_SERIES
    vs = np.where(small, 1.0, v)
    s0 = np.where(small, 1 - pv**2 / 6, np.sin(pv) / (np.pi * vs))
    e0 = np.exp(-0.5 * (v / sigma) ** 2)
    car = np.exp(1j * a * v)
    g0 = s0 * e0
    out = [car * g0]
    if orders > 1:
        s1 = np.where(small, -np.pi * pv / 3, (np.cos(pv) - s0) / vs)
        e1 = -v / sigma**2 * e0
        g1 = s1 * e0 + s0 * e1
        out.append(car * (g1 + 1j * a * g0))
    if orders > 2:
        s2 = np.where(small, -np.pi**2 / 3 + np.pi**2 * pv**2 / 10, -np.pi**2 * s0 - 2 * s1 / vs)
        e2 = (v**2 / sigma**4 - 1 / sigma**2) * e0
        out.append(car * (s2 * e0 + 2 * s1 * e1 + s0 * e2 + 2j * a * g1 - a * a * g0))
    return out


def corr_around(c, freqs, fs, lag, off, table=None):
    """Analytic correlation at lags ``lag[j] + off[l]`` samples: c (J, M, F), lag (J,), off (L,) → (J, M, L).

    The event's shift ``e^{j2πf lag/fs}`` is applied to its spectra, then all events share one (L, F)
    phasor table (``table``, :func:`offset_table`, or computed here): one matrix product instead of an
    einsum against (J, L, F) phasors.
    """
    j, m, n_f = c.shape
    dt = np.result_type(c, np.complex64)  # single-precision spectra stay single (a peak search)
    shifted = c * phasors(freqs, np.asarray(lag, float) / fs, dt)[:, None, :]
    table = phasors(freqs, np.asarray(off, float) / fs, dt) if table is None else table  # (L, F)
    return (shifted.reshape(j * m, n_f) @ table.T).reshape(j, m, len(off))


def offset_table(setup, off, dtype):
    """:func:`corr_around`'s (L, F) phasor table for the offsets ``off`` (samples), cached in ``setup``: the
    two-path fit looks around the same offsets seven times per event (~0.3 ms each at 48 kHz)."""
    cache = setup.setdefault("_offset_tables", {})
    key = (tuple(int(o) for o in off), np.dtype(dtype).str)
    if key not in cache:
        cache[key] = phasors(setup["freqs"], np.asarray(off, float) / setup["fs"], dtype)
    return cache[key]


def newton_peak(c, freqs, tau, phase=0.0, iters=2, max_step=None, sums=None):
    """Refine peaks of ``Re(e^{-jφ} r(τ))`` by Newton steps on the exact band-limited correlation.

    c : (..., Fb). tau : (...) start lags (s), within a fraction of a carrier period of the peak.
    sums : the moments to use (:class:`GridMoments`); None = :class:`BandMoments` of ``c``.
    Returns (tau, value) refined, same shapes.
    """
    sums = BandMoments(c, freqs) if sums is None else sums
    tau = np.array(tau, float)
    max_step = max_step if max_step is not None else 0.25 / freqs.max()
    rot = np.exp(-1j * phase)
    for _ in range(iters):
        _, z1, z2 = sums(tau) * rot
        d1, d2 = -np.imag(z1), -np.real(z2)
        step = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0)
        tau = tau + np.clip(step, -max_step, max_step)
    val = np.real(sums(tau, orders=1)[0] * rot)
    return tau, val


def newton_envelope(c, freqs, tau, iters=1, sums=None):
    """Refine peaks of the envelope ``|r(τ)|²`` by Newton steps on the exact band-limited correlation
    (the parabola through three samples is biased by a fraction of a sample, which would bias the
    carrier phase read at the peak). sums : as :func:`newton_peak`. Returns (tau, r(tau))."""
    sums = BandMoments(c, freqs) if sums is None else sums
    tau = np.array(tau, float)
    max_step = 0.25 / freqs.max()
    for _ in range(iters):
        m0, m1, m2 = sums(tau)
        z, z1, z2 = m0, 1j * m1, -m2
        d1 = 2 * np.real(np.conj(z) * z1)
        d2 = 2 * np.real(np.conj(z1) * z1 + np.conj(z) * z2)
        step = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0)
        tau = tau + np.clip(step, -max_step, max_step)
    return tau, sums(tau, orders=1)[0]


def _pulse_magnitude(setup, plain, over):
    """``|p|`` of one unit path at lags ``k / over`` samples, k = 0 .. nfft·over − 1 (circular), cached in
    ``setup`` (every chunk of an array's events, and both of :func:`locate`'s uses, share it)."""
    cache = setup.setdefault("_pulse_cache", {})
    key = (bool(plain), int(over))
    if key not in cache:
        nf = setup["nfft"] * over
        full = np.zeros(nf, complex)
        full[setup["kb"]] = setup["weights"] * (np.abs(setup["tmpl_conj"]) ** 2 if plain else 1.0)
        full /= full.sum()
        cache[key] = np.abs(sfft.ifft(full) * nf)
    return cache[key]


def pulse_near(setup, n, spread, plain=False, over=4):
    """Largest single-path pulse magnitude within ± ``spread`` samples of each lag 0..n−1: (n,) in [0, 1].

    Like :func:`pulse_envelope` but not made monotone: the exact sidelobe level a peak puts ``d`` samples
    away when its position is known to ± ``spread`` (sub-sample position, mics across the aperture).
    """
    p = _pulse_magnitude(setup, plain, over)
    p = np.r_[p[-(spread + 1) * over :], p[: (n + spread + 1) * over]]  # lags −spread−1 .. n+spread
    p = maximum_filter1d(p, 2 * spread * over + 1)
    return p[(spread + 1) * over :: over][:n]


def pulse_envelope(setup, n, plain=False):
    """Monotone envelope of a single path's correlation pulse at lags 0..n−1 samples: (n,) in [0, 1].

    A single path gives ``r(τ) = Σ_f w_f e^{j2πfτ} / Σ_f w_f`` (the band weights, after whitening); its
    magnitude, made non-increasing with |τ| (the running maximum from the far end), bounds how high a
    peak's sidelobes can reach ``n`` samples away. plain : the pulse of the unwhitened matched filter
    (weights × |S(f)|²).
    """
    p = _pulse_magnitude(setup, plain, 1)[: min(n, setup["nfft"])]
    return np.maximum.accumulate(p[::-1])[::-1]


SHADOW_MARGIN = 1.2  # a rejected peak above this × a later peak's exact sidelobe level gets a second look (CLEAN)


def direct_path_lag(env, pulse_env, snr_factor=6.0, min_ratio=0.05, sidelobe_margin=2.0, floor=None, peak=None,
                    near=None):
    """Direct path in a (J, T) array-averaged envelope: the earliest genuine onset above the noise floor.

    The strongest peak may be a reflection, arbitrarily later and stronger than the direct path (a
    reflection never precedes it). A peak at lag ``k`` counts as an arrival if it is a local maximum and
    - it exceeds ``snr_factor`` × the noise floor (median of the envelope before the strongest peak: the
      searched window starts well before any arrival) and ``min_ratio`` × the strongest peak;
    - it is not a sidelobe: it exceeds ``sidelobe_margin`` × what the later, stronger peaks' pulses can
      put there together (``pulse_env`` (L,), :func:`pulse_envelope`; the envelope of a sum of pulses is at
      most the sum of theirs: a cluster of strong paths raises ripples ahead of it that no single one of
      them explains. So a direct path 15 dB below a reflection 0.6 ms later still counts, while the
      pulses' own sidelobes do not). Earlier peaks are taken first, so sidelobes trailing a genuine
      arrival never matter.
    floor, peak : (J,) noise floor and strongest peak to use instead of this envelope's (after a reflection
    has been subtracted from it). near : (L,) :func:`pulse_near`; a rejected candidate above 1.2 × that
    exact sidelobe level is "shadowed" (worth a second look); None = every rejected candidate.
    Returns (J,) int lags, (J,) ratio direct / strongest peak, (J,) ratio direct / noise floor, (J,) bool
    "shadowed": a candidate before the chosen lag was rejected only as a possible sidelobe.
    """
    j, t = env.shape
    kmax = np.argmax(env, axis=1)
    out = kmax.copy()
    peak = env[np.arange(j), kmax] if peak is None else peak
    is_max = np.zeros_like(env, bool)
    is_max[:, 1:-1] = (env[:, 1:-1] >= env[:, :-2]) & (env[:, 1:-1] > env[:, 2:])
    floor = _prefix_medians(env, kmax) if floor is None else floor
    shadowed = np.zeros(j, bool)
    thr = np.maximum(snr_factor * np.asarray(floor, float), min_ratio * np.asarray(peak))
    above = is_max & (env >= thr[:, None]) & (np.arange(t)[None, :] < kmax[:, None])   # candidates before the peak
    rows = np.flatnonzero(np.any(above, axis=1))
    if rows.size:
        out[rows], shadowed[rows] = _first_onsets(env[rows], above[rows], kmax[rows], pulse_env, sidelobe_margin,
                                                  near)
    ratio = env[np.arange(j), out] / np.maximum(peak, 1e-300)
    snr = env[np.arange(j), out] / np.maximum(floor, 1e-300)
    return out, ratio, snr, shadowed


ONSET_SLOTS = 8   # candidates per row weighed at a time by :func:`_first_onsets` (most rows take their first)


def _first_onsets(env, above, kmax, pulse_env, sidelobe_margin, near):
    """:func:`direct_path_lag`'s choice among each row's candidates ``above`` (R, T) bool (local maxima above
    its thresholds before the strongest peak ``kmax`` (R,)): the earliest one that is no sidelobe of the later,
    stronger peaks (candidates and the maximum), else ``kmax``; and whether a candidate before it was rejected
    at above SHADOW_MARGIN × its exact sidelobe level (``near``; None: any rejected one). The rows advance
    together, ONSET_SLOTS candidates at a time, each undecided row's next ones against all its later peaks at
    once (the loop in tests/test_frontend_fast_paths.py: one row and candidate at a time; the sidelobe sums of
    the same terms in the same order, zeros between them). Returns ((R,) int, (R,) bool)."""
    r = len(kmax)
    n_c = above.sum(axis=1)
    c_max = int(n_c.max())
    valid = np.arange(c_max)[None, :] < n_c[:, None]                       # (R, C)
    cand = np.zeros((r, c_max), int)
    cand[valid] = np.nonzero(above)[1]                                      # each row's candidates, ascending
    strong = np.concatenate([cand, kmax[:, None]], axis=1)                  # ... and the maximum: (R, C + 1)
    s_valid = np.concatenate([valid, np.ones((r, 1), bool)], axis=1)
    e_s = np.take_along_axis(env, strong, axis=1)
    out, shadowed = kmax.copy(), np.zeros(r, bool)
    todo = np.arange(r)                                                     # rows not decided yet
    for s0 in range(0, c_max, ONSET_SLOTS):
        todo = todo[valid[todo, s0]]
        if not todo.size:
            break
        sl = slice(s0, min(s0 + ONSET_SLOTS, c_max))
        k, e_k, ok_k = cand[todo, sl], e_s[todo, sl], valid[todo, sl]           # (R', S)
        gap = strong[todo][:, None, :] - k[..., None]                           # (R', S, C + 1)
        later = s_valid[todo][:, None, :] & (gap > 0) & (e_s[todo][:, None, :] > e_k[..., None])
        lobe = np.where(later, e_s[todo][:, None, :] * pulse_env[np.clip(gap, 0, len(pulse_env) - 1)], 0.0)
        side = np.any(later, axis=2) & (e_k <= sidelobe_margin * np.sum(lobe, axis=2))
        shade = side
        if near is not None:
            exact = np.where(later, e_s[todo][:, None, :] * near[np.clip(gap, 0, len(near) - 1)], -np.inf)
            shade = side & (e_k > SHADOW_MARGIN * np.max(exact, axis=2))
        take = ok_k & ~side
        first = np.where(np.any(take, axis=1), np.argmax(take, axis=1), take.shape[1])   # S: none in this block
        shadowed[todo] |= np.any(shade & ok_k & (np.arange(take.shape[1])[None, :] < first[:, None]), axis=1)
        got = first < take.shape[1]
        out[todo[got]] = k[got, first[got]]
        todo = todo[~got]                                                       # possible sidelobes: look on
    return out, shadowed


def _prefix_medians(env, kmax, min_len=16):
    """(J,) the median of each row of ``env`` (J, T) before its lag ``kmax`` (J,) (the whole row where fewer than
    ``min_len`` samples precede it), as ``np.median`` row by row (the same values: the middle order statistics
    of each prefix, averaged in the envelope's precision), from one sort of all rows."""
    j, t = env.shape
    if not np.all(np.isfinite(env)):   # (np.median's NaN semantics: row by row)
        return np.array([np.median(e[:k] if k >= min_len else e) for e, k in zip(env, kmax)], float)
    n = np.where(kmax >= min_len, kmax, t)
    srt = np.sort(np.where(np.arange(t)[None, :] < n[:, None], env, np.inf), axis=1)
    rows = np.arange(j)
    mid = np.stack([srt[rows, (n - 1) // 2], srt[rows, n // 2]])
    return np.where(n % 2 == 1, mid[1], np.mean(mid, axis=0, dtype=env.dtype)).astype(float)


def subtract_path(c, setup, shape, lag, half_width):
    """Remove one path per mic from spectra (one step of CLEAN, exact in the frequency domain).

    c : (J, M, Fb) spectra whose single-path response is ``a · shape_f e^{−j2πfτ} / Σ shape``. lag : (J,)
    int lag of the path (samples); per mic its envelope peak within ± ``half_width`` is refined (Newton on
    the exact correlation), its complex amplitude read there, and that pulse subtracted. Returns a copy.
    """
    tau, a = _path_peaks(c, setup, lag, half_width)
    return c - path_model(setup, shape, tau, a, c.dtype)


def refine_peak_along(y, k):
    """Parabolic sub-sample peak positions along the last axis. y : (..., T), k : (...) int."""
    k = np.clip(k, 1, y.shape[-1] - 2)[..., None]
    a, b, c = (np.take_along_axis(y, k + d, axis=-1)[..., 0] for d in (-1, 0, 1))
    den = a - 2 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return k[..., 0] + np.clip(off, -0.5, 0.5)


def locate(c, setup, lo, hi, half_width, snr_factor=6.0, min_ratio=0.05, sidelobe_margin=2.0, gate=0,
           phase=None, reflection_ratio=0.5, c_onset=None, separate_pulses=4.0, separate_plain=True, smear=None, smear_max=None,
           own_phase=False, onset_env=None):
    """Direct path and sub-sample chirp start at every mic, for all events of one array.

    c : (J, M, Fb) spectra (:func:`segment_spectra`). lo, hi : lag samples searched for the direct path
    (the window should start before any possible arrival: its early part gives the noise floor).
    half_width : samples a mic's arrival may differ from the array's (aperture / c plus half a pulse).
    snr_factor, min_ratio, sidelobe_margin : :func:`direct_path_lag`. gate : extra lags kept around the
    window for the DOA. phase : carrier phase at the envelope peak (rad); None = estimate it from these
    measurements; own_phase : each event's own (:func:`_carrier_phase`; ``phase`` returned (J,)). reflection_ratio : a later peak at least this × the direct path's (and not its sidelobe)
    is a strong reflection (it ends the DOA gate). c_onset : (J, M, Fb) spectra for the onset search
    (the plain matched filter of :func:`segment_spectra`, whose response is causal); None = ``c``; onset_env its
    mic-averaged envelope on lags lo..hi if known (:func:`matched_stretch`). separate_pulses : a strong reflection
    within this many pulse widths (1 / bandwidth) of the direct path is modelled and subtracted before timing
    (:func:`separate_reflection`; 0 = never); separate_plain : do it on the plain matched filter (exact two-pulse
    model) rather than the whitened one. smear : samples by which the pulse is wider than the single-path model
    (a clock drift δ disperses a linear sweep's group delay by 2|δ|T: at 1e-3 and 0.5 s, 1 ms ≫ the pulse); the
    sidelobe model is widened by it. None = measured (:func:`excess_width`), at most ``smear_max`` if given.

    Returns a dict: ``dp`` (J,) int direct-path lag; ``tau`` (J, M) start lags (s since segment start);
    ``value`` (J, M) normalised carrier peak (1 = one clean path); ``phase``; ``r`` (J, M, T) analytic
    correlation on lags ``r_lo`` .. ``r_lo + T − 1``; ``ratio`` (J,) direct path / strongest peak;
    ``snr`` (J,) direct path / noise floor; ``strongest`` (J,) lag of the strongest peak;
    ``reflection`` (J,) lag of the first strong reflection after the direct path (−1: none seen);
    ``separated`` (J,) bool: that reflection was subtracted before timing; ``interference`` (J,) s
    (:func:`interference_sd`); with ``c_onset``, ``onset_env`` (J, hi − lo): the mic-averaged plain envelope
    the onset was searched in (before any second look; :func:`calib.frontend.nlos.earlier_paths` reuses it).
    """
    fs, freqs = setup["fs"], setup["freqs"]
    pad = gate + half_width + 2
    r_lo, r_hi = max(0, lo - pad), min(setup["nfft"], hi + pad)
    if c_onset is None:
        r, env, mean_env = _grid_envelopes(c, setup, r_lo, r_hi)  # (J, M, T)
        onset_env = mean_env[:, lo - r_lo : hi - r_lo]
    else:  # the whitened grid is needed only from the direct path on: computed once it is known
        r = env = mean_env = None
        onset_env = lag_grid(c_onset, setup, lo, hi, magnitude=True).mean(axis=1) if onset_env is None else onset_env
    pulse_env = pulse_envelope(setup, hi - lo + pad)
    onset_pulse = pulse_env if c_onset is None else pulse_envelope(setup, hi - lo, plain=True)
    if smear is None:
        smear = excess_width(onset_env, onset_pulse)
        smear = smear if smear_max is None else min(smear, smear_max)
    if smear > 0:  # a drifting clock stretches the chirp: its correlation pulse spreads by ~smear samples
        onset_pulse = np.r_[np.ones(smear), onset_pulse][: len(onset_pulse)]
    near = pulse_near(setup, hi - lo, 2 + smear, plain=c_onset is not None)
    dp, ratio, snr, shadowed = direct_path_lag(onset_env, onset_pulse, snr_factor, min_ratio, sidelobe_margin,
                                               near=near)
    strongest = lo + np.argmax(onset_env, axis=1)
    if np.any(shadowed):
        # a weak peak just before a strong one, at its sidelobe level: subtract the strong path from every
        # mic (both spectra) and look again (a direct path 15 dB below a reflection 0.6 ms later)
        c, c_onset, r, env, mean_env, dp, ratio, snr = _clean_strongest(
            c, c_onset, setup, shadowed, strongest, half_width, lo, hi, r_lo, r, onset_env, onset_pulse,
            (snr_factor, min_ratio, sidelobe_margin), dp, ratio, snr)
    dp = lo + dp
    if r is None:
        r_lo, (r, env, mean_env) = _late_grid_envelopes(c, setup, np.maximum(dp - pad, 0), r_hi)
    reflection = first_reflection(mean_env, dp - r_lo, half_width, pulse_env, reflection_ratio,
                                  sidelobe_margin)
    reflection = np.where(reflection >= 0, reflection + r_lo, -1)
    c, r, env, separated = _separate_close_reflection(c, c_onset, r, env, dp, reflection, setup, half_width, r_lo,
                                                      separate_pulses, separate_plain, smear)
    kk = _mic_peaks(env, dp, r_lo, half_width)  # (J, M)
    fc = np.sum(setup["weights"] * freqs) / np.sum(setup["weights"])
    tau0 = (refine_peak_along(env, kk) + r_lo) / fs
    # the Newton steps from the grid's samples (GridMoments) where they reach: the carrier peak may be half a
    # carrier period from the envelope's; r holds event j's lags from its pad before the direct path on
    grid = GridMoments(r, r_lo, setup)
    first = np.maximum(dp - pad, 0) - r_lo
    sums = grid if grid.covers(tau0, first, slack=int(np.ceil(0.5 * fs / fc)) + 2) else None
    env_tau, z = newton_envelope(c, freqs, tau0, sums=sums)
    phase, ph = _carrier_phase(z, phase, own_phase)
    # carrier peak nearest the envelope peak (within half a carrier period), then Newton
    dphi = np.angle(z * np.exp(-1j * ph))
    tau, val = newton_peak(c, freqs, env_tau - dphi / (2 * np.pi * fc), ph, sums=sums)
    interference = interference_sd(env.mean(axis=1), dp - r_lo, half_width, pulse_near(setup, r.shape[-1], 0), fc)
    return {"dp": dp, "tau": tau, "value": val, "phase": phase, "r": r, "r_lo": r_lo, "ratio": ratio,
            "interference": interference, "snr": snr, "strongest": strongest, "reflection": reflection,
            "separated": separated, **({} if c_onset is None else {"onset_env": onset_env})}


def _carrier_phase(z, phase, own_phase):
    """(phase, its broadcast against (J, M)): each event's own carrier phase (``own_phase``: a source moving
    during the sweep stretches each arrival differently, and a stretch rotates the phase, ~0.4 rad per 1e-4),
    else ``phase`` or, when None, the session's (:func:`estimate_phase`). z : (J, M) peak correlations."""
    if own_phase:
        phase = np.angle(np.sum(z, axis=1))
    elif phase is None:
        phase = estimate_phase(z)
    return phase, (np.asarray(phase)[:, None] if np.ndim(phase) else phase)


def _separate_close_reflection(c, c_onset, r, env, dp, reflection, setup, half_width, r_lo, separate_pulses,
                               separate_plain, smear=0):
    """A reflection within ``separate_pulses`` pulse widths biases the direct path's peak (a wall just
    behind the array: 10-25 µs): model both paths, subtract the reflection, time the direct path alone.
    A pulse dispersed by clock drift (``smear`` > 0) is no single-path pulse, so the two-path fit would
    split it: then only a strong reflection with a peak of its own (``reflection``) is separated. A smear below
    SMEAR_SPLIT pulse widths (a crystal's 1e-4 over a 0.5 s sweep: 0.1 ms) leaves the pulse nearly a single
    path's: the fit runs, a second path stronger than the first rejected (the smear's own split).
    Returns (c, r, env, separated (J,) bool) with the affected events' spectra and correlations updated."""
    freqs = setup["freqs"]
    separated = np.zeros(len(dp), bool)
    if separate_pulses <= 0 or not len(dp):
        return c, r, env, separated
    n_pulse = setup["fs"] / max(freqs.max() - freqs.min(), 1.0)
    src, shape = (c, setup["weights"]) if c_onset is None or not separate_plain else \
        (c_onset, setup["weights"] * np.abs(setup["tmpl_conj"]) ** 2)
    if smear > SMEAR_SPLIT * n_pulse:
        separated = (reflection >= 0) & (reflection - dp <= separate_pulses * n_pulse)
        if not np.any(separated):
            return c, r, env, separated
        sel = np.flatnonzero(separated)
        c = c.copy()
        c[sel] = separate_reflection(src[sel], setup, shape, dp[sel], reflection[sel], half_width)
        r = r.copy()
        r[sel] = lag_grid(c[sel], setup, r_lo, r_lo + r.shape[-1])
        return c, r, np.abs(r), separated
    *fit, gain = two_path_fit(src, setup, shape, dp, half_width, separate_pulses * n_pulse)
    separated = np.median(gain, axis=1) >= CLOSE_RATIO ** 2
    if not np.any(separated):
        return c, r, env, separated
    cand = np.flatnonzero(separated)
    t1, a1, t2, a2 = refine_two_paths(src[cand], setup, shape, *(x[cand] for x in fit))
    rho = np.median(np.abs(a2) / np.maximum(np.abs(a1), 1e-300), axis=1)
    # a smeared pulse (0 < smear ≤ SMEAR_SPLIT pulses) splits into a weak leading "path" and a strong one just
    # after it (ushape seed 66, A3: 0.5 pulse widths apart, the second 2.4-4.5× the first: timed 40 µs early);
    # there a second path counts only if it is no stronger than the first
    ok = (rho >= CLOSE_RATIO) & ((smear <= 0) | (rho <= 1.0))
    separated[cand] = ok
    if not np.any(ok):
        return c, r, env, separated
    sel = cand[ok]
    c = c.copy()
    c[sel] = src[sel] - path_model(setup, shape, t2[ok], a2[ok], src.dtype)
    r = r.copy()
    r[sel] = lag_grid(c[sel], setup, r_lo, r_lo + r.shape[-1])
    return c, r, np.abs(r), separated


def _mic_peaks(env, dp, r_lo, half_width):
    """Per mic, the envelope peak (lag index (J, M) into ``env``) within the lags the aperture allows
    around the array's direct path ``dp``: a local maximum if there is one (the rising flank of a strong
    reflection just outside does not count)."""
    k = np.arange(r_lo, r_lo + env.shape[-1])
    allowed = (np.abs(k[None, :] - dp[:, None]) <= half_width)[:, None, :]  # (J, 1, T)
    local = np.zeros_like(env, bool)
    local[..., 1:-1] = (env[..., 1:-1] >= env[..., :-2]) & (env[..., 1:-1] > env[..., 2:])
    use_local = np.any(allowed & local, axis=-1, keepdims=True)
    mask = allowed & (local | ~use_local)
    return np.argmax(np.where(mask, env, -1.0), axis=-1)


def _clean_strongest(c, c_onset, setup, shadowed, strongest, half_width, lo, hi, r_lo, r, onset_env,
                     onset_pulse, onset_args, dp, ratio, snr):
    """:func:`locate`'s second look at events with a shadowed candidate: the strongest path subtracted
    (:func:`subtract_path`) from the timing spectra and the onset spectra, the onset searched again with
    the first look's noise floor and strongest peak. Returns updated copies (``r`` None: none, not computed
    yet)."""
    sel = np.flatnonzero(shadowed)
    floor = onset_env[sel, dp[sel]] / snr[sel]
    peak = onset_env[sel, dp[sel]] / ratio[sel]
    c_sub = subtract_path(c[sel], setup, setup["weights"], strongest[sel], half_width)
    on_sub = None
    if c_onset is not None:
        plain_shape = setup["weights"] * np.abs(setup["tmpl_conj"]) ** 2
        on_sub = subtract_path(c_onset[sel], setup, plain_shape, strongest[sel], half_width)
    env2 = lag_grid(c_sub if on_sub is None else on_sub, setup, lo, hi, magnitude=True).mean(axis=1)
    d2, q2, s2, _ = direct_path_lag(env2, onset_pulse, *onset_args, floor=floor, peak=peak)
    # keep the second look only where it found an arrival clearly before the subtracted path
    better = (d2 < strongest[sel] - lo - half_width) & (q2 >= onset_args[1]) & (s2 >= onset_args[0])
    dp, ratio, snr = dp.copy(), ratio.copy(), snr.copy()
    keep = sel[better]
    dp[keep], ratio[keep], snr[keep] = d2[better], q2[better], s2[better]
    c = c.copy()
    c[keep] = c_sub[better]
    if c_onset is not None:
        c_onset = c_onset.copy()
        c_onset[keep] = on_sub[better]
    if r is None:  # the whitened grid is not computed yet
        return c, c_onset, None, None, None, dp, ratio, snr
    r = r.copy()
    if keep.size:
        r[keep] = lag_grid(c[keep], setup, r_lo, r_lo + r.shape[-1])
    env = np.abs(r)
    return c, c_onset, r, env, env.mean(axis=1), dp, ratio, snr


def _grid_envelopes(c, setup, r_lo, r_hi):
    """The correlation on lags ``r_lo .. r_hi − 1`` (:func:`lag_grid`), its magnitude and mic average."""
    r = lag_grid(c, setup, r_lo, r_hi)
    env = np.abs(r)
    return r, env, env.mean(axis=1)


GRID_GROUP_SLACK = 64  # samples: events whose window starts this much before the median one's form a group


def _late_grid_envelopes(c, setup, first, r_hi):
    """:func:`_grid_envelopes` on lags ``min(first) .. r_hi − 1`` where only lags ``first[j] ..`` of event
    j are needed (the timing reads nothing before its direct path's pad): the events whose window starts
    near the median one's on their group's shortest common range, the earlier ones on theirs; the unneeded
    lags stay 0. In rooms one early direct path in a chunk otherwise made every event's grid span the
    whole search window (~30 × longer). Returns (r_lo, (r, env, mean_env))."""
    first = np.asarray(first, int)
    r_lo = int(np.min(first)) if first.size else 0
    late = first >= np.median(first) - GRID_GROUP_SLACK if first.size else np.zeros(0, bool)
    if np.all(late) or not np.any(late):
        return r_lo, _grid_envelopes(c, setup, r_lo, r_hi)
    r = np.zeros(c.shape[:-1] + (r_hi - r_lo,), np.complex64)
    for group in (late, ~late):
        g_lo = int(np.min(first[group]))
        r[group, :, g_lo - r_lo :] = lag_grid(c[group], setup, g_lo, r_hi)
    env = np.abs(r)
    return r_lo, (r, env, env.mean(axis=1))


def _path_peaks(c, setup, lag, half_width):
    """Per mic, the envelope peak within ± ``half_width`` samples of ``lag`` (J,), refined: (tau, amp) (J, M)."""
    fs = setup["fs"]
    off = np.arange(-half_width - 1, half_width + 2)  # lags around each path, evaluated exactly
    lags = np.asarray(lag)[:, None] + off[None, :]  # (J, L)
    table = offset_table(setup, off, np.result_type(c, np.complex64))
    r = np.abs(corr_around(c, setup["freqs"], fs, lag, off, table))  # (J, M, L)
    kk = np.argmax(r[..., 1:-1], axis=-1) + 1
    return newton_envelope(c, setup["freqs"], (refine_peak_along(r, kk) + lags[:, :1]) / fs, iters=2)


def separate_reflection(c, setup, shape, dp, refl, half_width, iters=3):
    """Remove a reflection that overlaps the direct path's pulse (SAGE-style alternating two-path fit).

    c : (J, M, Fb) spectra whose single path of amplitude ``a`` at ``τ`` is ``a · shape_f e^{−j2πfτ} / Σ
    shape`` (exact for the plain matched filter). dp, refl : (J,) lags of the direct path and of the
    reflection. Each path is re-estimated per mic (envelope peak, Newton) with the other's current model
    subtracted, ``iters`` times. Returns c with the reflection's model subtracted.
    """
    def model(tau, a):
        return path_model(setup, shape, tau, a, c.dtype)

    t1, a1 = _path_peaks(c, setup, dp, half_width)
    for _ in range(iters):
        t2, a2 = _path_peaks(c - model(t1, a1), setup, refl, half_width)
        t1, a1 = _path_peaks(c - model(t2, a2), setup, dp, half_width)
    return c - model(t2, a2)


SMEAR_SPLIT = 0.5        # a pulse smeared by less than this many pulse widths is still fitted as one path (two-path fit)
CLOSE_RATIO = 0.15       # a second path fitted at ≥ this × the direct path's amplitude (median over mics) is removed
CLOSE_MAX_OVERLAP = 0.8  # ... if its pulse overlaps the direct one's less than this (|p(Δ)|; closer: inseparable)
GRID_OVER = 4            # at most this many sub-sample steps per sample in the two-path fit's grid, and
GRID_PER_PULSE = 18      # about this many per pulse width (16 kHz, 3.5 kHz of band: 4 per sample, as
                         # for 48 kHz and 9.5 kHz; 48 kHz and 3.5 kHz: 1 per sample, not 55 per pulse)


def pulse_response(setup, shape, n, over):
    """Correlation ``p(Δ) = Σ_f u_f e^{j2πfΔ}`` (u = shape / Σ shape) of one unit path at lags
    ``Δ = 1/over .. n/over`` samples: (n,) complex."""
    unit = (shape / shape.sum())[None, None, :]
    return lag_grid(unit, setup, 1.0 / over, (n + 1.0) / over, 1.0 / over)[0, 0].astype(np.complex128)


def _two_path_search(b, pd, d, n1):
    """Grid index (J, M) into (n1, D) of the pair explaining the most energy, ``(|b1|² + |b2|² −
    2 Re(p b1 conj(b2))) / (1 − |p|²)`` with ``b1 = b[i]``, ``b2 = b[i + d]``, ``p = pd``: single
    precision, one event at a time (its (M, n1, D) grid stays in cache), amplitudes never formed; the
    separations ``d`` are consecutive (where the pulses overlap less than a bound), so ``b[i + d]`` is a
    strided window of ``b``, not a gathered copy."""
    pw = b.real ** 2 + b.imag ** 2
    n_d = len(d)
    consecutive = n_d and np.all(np.diff(d) == 1)
    idx2 = None if consecutive else np.arange(n1)[:, None] + d[None, :]         # (n1, D)
    inv_det = (1.0 / (1.0 - np.abs(pd) ** 2)).astype(np.float32)
    p2 = (2 * pd).astype(np.complex64)
    k = np.zeros(b.shape[:2], int)
    for j in range(b.shape[0]):
        if consecutive:
            b2 = np.lib.stride_tricks.sliding_window_view(b[j, :, d[0] : d[0] + n1 + n_d - 1], n_d, axis=-1)
            w2 = np.lib.stride_tricks.sliding_window_view(pw[j, :, d[0] : d[0] + n1 + n_d - 1], n_d, axis=-1)
        else:
            b2, w2 = b[j][:, idx2], pw[j][:, idx2]
        cross = np.conj(b2) * p2                                                 # (M, n1, D): 2 p conj(b2)
        cross *= b[j, :, :n1, None]
        e = pw[j, :, :n1, None] + w2
        e -= cross.real
        e *= inv_det
        k[j] = np.argmax(e.reshape(len(e), -1), axis=-1)
    return k


def two_path_fit(c, setup, shape, dp, half_width, max_sep, over=None):
    """Direct path plus the strongest later path within ``max_sep`` samples, per mic, by a grid search.

    c : (J, M, Fb) spectra whose single path of amplitude ``a`` at ``τ`` is ``a · u_f e^{−j2πfτ}``
    (u = shape / Σ shape; exact for the plain matched filter). With the correlation ``b(τ) = Σ_f c_f
    e^{j2πfτ}`` and the pulse ``p``, the least-squares amplitudes of paths at ``τ1 < τ2`` (in the metric
    weighted by 1/u) solve ``[[1, p(−Δ)], [p(Δ), 1]] a = [b(τ1), b(τ2)]``, ``Δ = τ2 − τ1``, and explain the
    energy ``Re(b^H a)``; the pair explaining the most over ``τ1`` within ``dp ± half_width`` and ``Δ``
    from where the pulses overlap less than ``CLOSE_MAX_OVERLAP`` up to ``max_sep`` wins (variable projection:
    no iteration, no starting values). A reflection overlapping the direct path's pulse (a wall a few
    cm to 20 cm behind the array) shows as no separate peak, yet moves the direct path's peak and phase.
    Returns t1, a1, t2, a2 (J, M): times (s since the segment start) and complex amplitudes, and the
    energy the second path explains beyond the best single path (refined off the grid) relative to it.
    over : grid steps per sample (None: ``GRID_PER_PULSE`` per pulse width, at most ``GRID_OVER``).
    """
    fs = setup["fs"]
    if over is None:  # grid steps per sample: GRID_PER_PULSE per pulse width, at most GRID_OVER per sample
        pulse = fs / max(setup["freqs"].max() - setup["freqs"].min(), 1.0)
        over = int(np.clip(round(GRID_PER_PULSE / pulse), 1, GRID_OVER))
    p_all = pulse_response(setup, shape, int(max_sep * over), over)   # p(Δ); p(−Δ) = conj
    d = np.flatnonzero(np.abs(p_all) < CLOSE_MAX_OVERLAP) + 1
    d = d if d.size else np.array([len(p_all)])
    pd = p_all[d - 1]
    n1 = (2 * half_width + 1) * over
    lo = np.asarray(dp) - half_width
    # every event's lags from its own lo: shift the spectra, then one transform for all
    c_lo = c * phasors(setup["freqs"], lo / fs, np.result_type(c, np.complex64))[:, None, :]
    b = lag_grid(c_lo, setup, 0, (n1 + d[-1]) / over, 1.0 / over)  # (J, M, n1 + d_max) complex64
    # explained energy Re(b^H a) = (|b1|² + |b2|² − 2 Re(p b1 conj(b2))) / (1 − |p|²): searched in single
    # precision without forming the amplitudes on the (n1, D) grid; the winner is recomputed exactly
    k = _two_path_search(b, pd, d, n1)
    i1, i2 = np.unravel_index(k, (n1, len(d)))
    t1 = (lo[:, None] + i1 / over) / fs
    t2 = t1 + d[i2] / over / fs
    b1 = np.take_along_axis(b, i1[..., None], axis=-1)[..., 0].astype(np.complex128)
    b2 = np.take_along_axis(b, (i1 + d[i2])[..., None], axis=-1)[..., 0].astype(np.complex128)
    p, dt = pd[i2], 1.0 - np.abs(pd[i2]) ** 2
    a1, a2 = (b1 - np.conj(p) * b2) / dt, (b2 - p * b1) / dt
    best = np.real(np.conj(b1) * a1 + np.conj(b2) * a2)
    # the best single path, refined off the grid: the second path must explain energy it cannot
    k1 = np.argmax(np.abs(b[..., :n1]), axis=-1)
    _, z1 = newton_envelope(c, setup["freqs"], (lo[:, None] + k1 / over) / fs, iters=1)
    gain = (best - np.abs(z1) ** 2) / np.maximum(np.abs(z1) ** 2, 1e-300)
    return t1, a1, t2, a2, gain


def path_model(setup, shape, tau, a, dtype=np.complex128):
    """Spectra (..., Fb) of paths of complex amplitudes ``a`` (...) at ``tau`` (...) s: ``a u_f e^{−j2πfτ}``
    (``dtype``: that of the spectra it is subtracted from)."""
    out = phasors(setup["freqs"], -tau, dtype)
    out *= (shape / shape.sum()).astype(out.real.dtype)
    out *= a[..., None].astype(dtype)
    return out


def refine_two_paths(c, setup, shape, t1, a1, t2, a2, iters=3):
    """Refine a two-path fit (:func:`two_path_fit`, on a grid) by alternating Newton steps on each path's
    envelope with the other's model subtracted (exact at the fixed point for two paths; a single path
    drives the second amplitude to ~0). The moments come from each event's lag grid around the pair and the
    pulse's (:class:`_LessPath`): no band-wide model is formed or subtracted (the same values as doing so to
    single precision, ~1e-6 of the peak; 0.52 → 0.31 s CPU on robot 350). Returns t1, a1, t2, a2 refined."""
    freqs, fs = setup["freqs"], setup["fs"]
    # Newton moves each path by at most 0.25 / f_max per step: both stay within this many samples of their start
    move = int(np.ceil(2 * (iters + 1) * 0.25 / freqs.max() * fs))
    own = _event_grid_moments(c, setup, np.minimum(t1, t2), np.maximum(t1, t2), move)
    pulse = pulse_moments(setup, shape, int(np.ceil(np.max(np.abs(t2 - t1), initial=0.0) * fs)) + 2 * move)
    for _ in range(iters):
        t2, a2 = newton_envelope(None, freqs, t2, iters=1, sums=_LessPath(own, pulse, t1, a1))
        t1, a1 = newton_envelope(None, freqs, t1, iters=1, sums=_LessPath(own, pulse, t2, a2))
    return t1, a1, t2, a2


class _LessPath:
    """The moments of spectra less one path's model, ``c − path_model(t_o, a_o)``, without forming it: by
    linearity ``Σ c ω^k e^{jωτ} − a_o P_k(τ − t_o)`` with the path's pulse ``P`` (:func:`pulse_moments`).
    own : the moments of ``c`` (``(tau, orders) → (orders, ...)``, :func:`_event_grid_moments`); t_o, a_o
    (...) the path's times (s) and amplitudes."""

    def __init__(self, own, pulse, t_o, a_o):
        self.own, self.pulse, self.t_o, self.a_o = own, pulse, t_o, a_o

    def __call__(self, tau, orders=3):
        return self.own(tau, orders) - self.a_o * self.pulse(np.asarray(tau, float) - self.t_o, orders)


def _event_grid_moments(c, setup, first, last, margin):
    """Moments of the spectra ``c`` (J, M, Fb) at lags within ``margin`` samples of ``first .. last`` (J, M) s:
    :class:`GridMoments` on each event's own lag grid (its spectra shifted to its first lag, then one
    :func:`lag_grid` for all), instead of sums over the band's bins at every evaluation. Returns a callable
    ``(tau (J, M), orders) → (orders, J, M)``."""
    fs = setup["fs"]
    pad = margin + _kernel_half_length(setup) + 2
    lo = np.floor(np.min(first, axis=-1) * fs).astype(int) - pad                     # (J,)
    span = int(np.max(np.ceil(np.max(last, axis=-1) * fs).astype(int) + pad - lo, initial=1))
    shifted = c * phasors(setup["freqs"], lo / fs, np.result_type(c, np.complex64))[:, None, :]
    grid = GridMoments(lag_grid(shifted, setup, 0, span), 0.0, setup)
    return lambda tau, orders=3: grid(np.asarray(tau, float) - (lo / fs)[:, None], orders)


def _kernel_half_length(setup):
    """Taps on either side of a lag that :class:`GridMoments` reads (its kernel's half-length ``g``)."""
    return GridMoments(np.zeros(1), 0.0, setup).g


def pulse_moments(setup, shape, reach):
    """:class:`GridMoments` of one unit path's correlation ``P(Δ) = Σ_f u_f e^{j2πfΔ}`` (u = shape / Σ shape,
    :func:`path_model`'s) on the lags within ``reach`` samples (and the kernel's taps) of 0, exact in double
    precision from the full inverse transform; evaluated at any ``Δ`` (...) s within. Cached in ``setup`` per
    shape (the plain or the whitened pulse) and reach (rounded up to a power of two)."""
    cache = setup.setdefault("_pulse_moments", {})
    span = 1 << int(np.ceil(np.log2(max(reach, 1) + _kernel_half_length(setup) + 2)))
    key = (hash(np.asarray(shape).tobytes()), span)
    if key not in cache:
        full = np.zeros(setup["nfft"], complex)
        full[setup["kb"]] = shape / np.sum(shape)
        p = sfft.ifft(full) * setup["nfft"]                     # p[n] = P(n / fs), circular
        cache[key] = GridMoments(np.r_[p[-span:], p[: span + 1]], -span, setup)
    return cache[key]


SKIRT_LEVEL = 0.2  # excess_width compares the leading skirt of the strongest peak down to this height
SKIRT_RISE = 0.02  # ... as long as it keeps falling (within this relative ripple)


def excess_width(env, pulse_env, level=SKIRT_LEVEL):
    """How much further (samples) the strongest peak's leading skirt reaches down to ``level`` × its height
    than a single path's: the median over events (J, T) of the excess, ≥ 0. A drifting clock's dispersion
    gives every event's pulse a long leading ramp (at δ = 8e-4, 0.5 s: 0.2 of the peak 9 samples ahead,
    where the model pulse is below 0.2 after 4); only the leading side is used, reverberation widens the other,
    and only as long as it keeps falling: a weak direct path ahead of a reflection is a peak of its own.
    """
    model = int(np.sum(pulse_env >= level)) - 1
    out = []
    for e in env:
        k = int(np.argmax(e))
        i = k  # walk down the leading side while it keeps falling (a separate earlier peak ends the skirt)
        while i > 0 and e[i - 1] >= level * e[k] and e[i - 1] <= e[i] * (1 + SKIRT_RISE):
            i -= 1
        out.append(k - i - model)
    excess = int(np.median(out)) if out else 0
    return excess if excess > 1 else 0  # ± 1 sample: the measure's own resolution


def interference_sd(env, dp, half_width, pulse, fc):
    """Timing error (s, RMS) that the later paths' sidelobes put on the direct path's carrier peak.

    A path ``ρ`` times the direct path's height, ``Δ`` samples later, adds ``ρ |p(Δ)|`` (``pulse`` (L,),
    the exact single-path pulse magnitude) at the direct path; its carrier slope shifts the peak by
    ``ρ |p(Δ)| sin ψ / (2π f_c)`` with an unknown phase ψ: RMS ``/ √2``, paths adding in power. Common to
    all mics of a small array, so the spread between mics does not see it. env : (J, T) mic-averaged
    envelope, dp : (J,) lags into it. Returns (J,).
    """
    j, t = env.shape
    out = np.zeros(j)
    is_max = np.zeros_like(env, bool)
    is_max[:, 1:-1] = (env[:, 1:-1] >= env[:, :-2]) & (env[:, 1:-1] > env[:, 2:])
    for i in range(j):
        q = np.flatnonzero(is_max[i, dp[i] + half_width + 1 :]) + dp[i] + half_width + 1
        d = np.minimum(q - dp[i], len(pulse) - 1)
        # a path's height above the direct path's own sidelobe there (its sidelobes are no other path)
        rho = np.maximum(env[i, q] / max(env[i, dp[i]], 1e-300) - pulse[d], 0.0)
        out[i] = np.sqrt(np.sum((rho * pulse[d]) ** 2)) / (2 * np.pi * fc * np.sqrt(2))
    return out


def first_reflection(env, dp, half_width, pulse_env, ratio=0.5, sidelobe_margin=2.0):
    """First strong reflection after the direct path in a (J, T) envelope: the earliest local maximum
    more than ``half_width`` samples after ``dp`` (J,) that reaches ``ratio`` × the direct path's height and
    is not the direct path's sidelobe. Returns (J,) int lags (−1: none)."""
    j, t = env.shape
    out = np.full(j, -1)
    is_max = np.zeros_like(env, bool)
    is_max[:, 1:-1] = (env[:, 1:-1] >= env[:, :-2]) & (env[:, 1:-1] > env[:, 2:])
    for i in range(j):
        d0 = env[i, dp[i]]
        ks = np.arange(dp[i] + half_width + 1, t)
        if not ks.size:
            continue
        side = sidelobe_margin * d0 * pulse_env[np.minimum(ks - dp[i], len(pulse_env) - 1)]
        hit = np.flatnonzero(is_max[i, ks] & (env[i, ks] >= ratio * d0) & (env[i, ks] > side))
        if hit.size:
            out[i] = ks[hit[0]]
    return out


def estimate_phase(z):
    """Session phase of the received chirp relative to the template: weighted circular mean of the
    phases of the correlation at the envelope peaks. z : complex array (any shape)."""
    z = np.asarray(z).ravel()
    return float(np.angle(np.sum(z))) if z.size else 0.0


def fuse_times(t_origin, spread_floor=2e-6, path_gap=None):
    """Robust fusion of per-mic times referred to the array origin.

    t_origin : (J, M) seconds (NaN = unusable). The median, then the mean of the mics within 3 robust
    standard deviations of it (efficient for Gaussian errors, immune to a mic locked on a wrong peak).
    path_gap : s, or None. Mics locked on different paths: where the times split into groups more than
    ``path_gap`` apart, only the earliest group of at least :func:`min_path_group` mics is fused (a
    reflection is later than the direct path, never earlier; see :func:`earliest_path_group`).
    Returns (J,) fused times, (J,) standard error estimates (s) and the (J, M) mask of the mics fused.
    """
    use = np.isfinite(t_origin)
    if path_gap is not None:
        use &= earliest_path_group(t_origin, path_gap)
    t_use = np.where(use, t_origin, np.nan)
    med = np.nanmedian(t_use, axis=1)
    dev = np.abs(t_use - med[:, None])
    mad = mad_std(t_use, axis=1, center=med[:, None])
    keep = dev <= 3 * np.maximum(mad, spread_floor)[:, None]
    n = keep.sum(axis=1)
    t = np.where(keep, t_use, 0.0).sum(axis=1) / np.maximum(n, 1)
    res = np.where(keep, t_use - t[:, None], 0.0)
    sd = np.sqrt((res**2).sum(axis=1) / np.maximum(n - 1, 1))
    return t, sd / np.sqrt(np.maximum(n, 1)), keep


def min_path_group(m):
    """Fewest mics (of ``m``) that make a path group in :func:`earliest_path_group`: two, and a third of them
    (one mic early on noise or a sidelobe is no group; every mic of a 2-mic pair must agree)."""
    return max(2, int(np.ceil(m / 3)))


def earliest_path_group(t_origin, gap):
    """(J, M) bool: per event, the mics of the earliest group of at least :func:`min_path_group` finite times
    with no gap above ``gap`` (s) inside it; every finite mic where the times do not split so.

    A reflection a pulse width or so after the direct path merges with it in the array's envelope; per mic,
    the refined peak then lands on one path or the other (lshape seed 10, A3: three mics on the direct path,
    three 370 µs later on a reflection; their median was 188 µs late). Mics on one path agree to a few µs
    once referred to the origin; two paths resolve only ~half a pulse width (1 / 2B) apart, so groups
    further apart are different paths, and the earliest is the direct one."""
    t = np.asarray(t_origin, float)
    out = np.isfinite(t)
    spread = np.nanmax(t, axis=1) - np.nanmin(t, axis=1) if t.size else np.zeros(len(t))
    need = min_path_group(t.shape[1]) if t.ndim == 2 else 2
    for j in np.flatnonzero(np.nan_to_num(spread) > gap):
        order = np.argsort(np.where(out[j], t[j], np.inf))[: int(out[j].sum())]
        cuts = np.flatnonzero(np.diff(t[j, order]) > gap) + 1
        groups = np.split(order, cuts)
        first = next((g for g in groups if len(g) >= need), None)
        if first is not None and len(groups) > 1:
            out[j] = False
            out[j, first] = True
    return out


def drift_bias(template, fs, band, locate_kw, pre, seg_len, whiten_hz=500.0, delta=2e-5):
    """``β``: how far (s per unit drift) a chirp recorded on a clock running ``1 + δ`` fast moves this
    estimator's arrival time: ``measured = true_start + β δ``.

    A clock running fast records the chirp stretched in time (``s(t / (1 + δ))``), and a chirp's matched
    filter trades that stretch for delay (range–Doppler coupling). Measured on the template itself,
    stretched exactly (band-limited FFT resampling) by ``±δ``, through :func:`locate` with the settings of
    the real measurement (``locate_kw``; ``pre`` = lag of the expected start in a segment of ``seg_len``
    samples); the central difference removes any constant offset of the estimator. ``δ`` must stay in the
    linear range: the delay–Doppler coupling of a wide-band sweep bends beyond a stretch of ~1e-4 (a
    500–10000 Hz, 0.5 s sweep gave 0.657 s at 1e-3 instead of 0.526 s), so the default is 2e-5, realised
    exactly by zero-padding the buffer to ≥ 1/δ samples (one sample of stretch). For any sweep β equals the
    band-weighted mean of ``d(f τ_g(f))/df`` (``τ_g`` the template's group delay; tests check both).
    """
    (s1, s2), (d1, d2) = stretch_shifts(template, fs, band, locate_kw, pre, seg_len, whiten_hz, (delta, -delta))
    return float((s1 - s2) / (d1 - d2))


def sweep_time(template, fs, band, locate_kw, pre, seg_len, whiten_hz, beta, up=16):
    """``t*`` (s after the sweep start): the instant of the sweep whose stretch this estimator's arrival
    follows. A source moving during the sweep stretches it by ``1 + ṙ(t)/c``; with the range accelerating
    (``r̈ = α c``: the path's curvature, the robot speeding up) the delay grows as ``ε t + ½ α t²`` and the
    arrival moves by ``β (ε + α t*)``. Even weights over a linear sweep give ``T/2``; the envelope peak weighs
    the band's middle more (0.44 T for a 0.5 s, 0.5-4 kHz sweep). Measured as β is, on the template received
    with the delay ``± ½ α t²`` (central difference, :func:`delay_shift`). ``beta`` : :func:`drift_bias`.
    α keeps the group delay's spread over the sweep (``~1.5 α T²``) at a quarter pulse: linear (at 4× that,
    t* came out 0.51 T)."""
    alpha = 0.25 / ((band[1] - band[0]) * 1.5 * (len(template) / fs) ** 2)
    s1, s2 = (delay_shift(template, fs, band, locate_kw, pre, seg_len, whiten_hz, lambda t, a=a: 0.5 * a * t ** 2, up)
              for a in (alpha, -alpha))
    return float((s1 - s2) / (2 * alpha * beta))


def delay_shift(template, fs, band, locate_kw, pre, seg_len, whiten_hz, delay, up=16):
    """This estimator's arrival (s, lag from the expected start ``pre``) for the template received with the
    time-varying delay ``delay(t)`` (s; t s after the sweep start, ``delay(0) = 0``, |delay'| ≪ 1): each
    sample's emission time solved by a fixed point and the template evaluated there by band-limited
    interpolation (×``up`` by FFT, then cubic: :func:`_cubic_at`). A source moving during the sweep: ``delay(t) = (r(t) −
    r(0)) / c`` (:func:`sweep_time` takes the quadratic part; benchmarks/diag_moving_arrivals.py the cubic
    one, the range's jerk over the sweep)."""
    n = len(template)
    fine = _fine_template(np.asarray(template, float).tobytes(), int(up))
    setup = spectra_setup(template, fs, band, seg_len, whiten_hz)
    u = (np.arange(seg_len) - pre) / fs
    te = u.copy()
    for _ in range(4):   # emission time of each sample: u = te + delay(te) (fixed point, |delay'| ≪ 1)
        te = u - delay(np.clip(te, 0, None))
    y = np.where((te >= 0) & (te < n / fs), _cubic_at(fine, np.clip(te, 0, None) * (fs * up)), 0.0)
    return float(locate(segment_spectra(y[None, :], np.zeros(1, int), setup), setup, **locate_kw)["tau"][0, 0])


@lru_cache(maxsize=2)
def _fine_template(template_bytes, up):
    """The template (float64 bytes) by band-limited interpolation at ``up`` × its rate, one period of the periodic
    signal (:func:`delay_shift`; both of :func:`sweep_time`'s delays share it). Zero-padded by at least 8 samples
    (faded to 0 at both ends: its periodic interpolation does not wrap) to a 2·3·5-smooth length: the former 8
    zeros made a 0.5 s template at 48 kHz 24008 = 8 · 3001 samples, whose transforms (the one ×16 long) took 15x
    longer, a prime factor that large."""
    t = np.frombuffer(template_bytes, float)
    buf = np.zeros(sfft.next_fast_len(len(t) + 8, real=True))
    buf[: len(t)] = t
    return fourier_resample(buf, up * len(buf))


def _cubic_at(y, x):
    """``y`` (one period of a periodic signal, N samples) at fractional sample positions ``x``: 4-point Lagrange
    (cubic) interpolation. On a band-limited signal oversampled 16× (:func:`_fine_template`) its error is ~2e-6 of
    the amplitude at the band's top (a 4 kHz sweep at 16 kHz); the cubic spline it replaced was within ~3e-7 but
    cost a spline fit over the whole ×16 template and scipy.interpolate's import (~0.25 s of CPU) in the
    frontend: :func:`sweep_time` moved by 1-2e-8 s (a 0.5 s sweep)."""
    k = np.floor(x).astype(np.int64)
    f = x - k
    w = ((-f * (f - 1) * (f - 2) / 6), ((f + 1) * (f - 1) * (f - 2) / 2), (-(f + 1) * f * (f - 2) / 2),
         ((f + 1) * f * (f - 1) / 6))
    return sum(wi * np.take(y, k + d, mode="wrap") for wi, d in zip(w, (-1, 0, 1, 2)))


def doa_time(template, setup):
    """When (s after the sweep start) the DOA of a source moving during the sweep looks: the SRP-PHAT peak is
    the least-squares fit of the per-frequency directions, each frequency weighted by its band weight × f²
    (the phase differences between mics grow with f), and a sweep passes frequency f at its group delay
    t(f): the weighted mean of t(f). A 0.5 s, 0.5-4 kHz linear sweep: 0.33 s (the DOAs of the moving preset
    fitted best at 0.32 s: 0.02-0.14° against 0.24-0.58° at T/2, anechoic)."""
    n = sfft.next_fast_len(4 * len(template), real=True)   # bins fine enough that the phase steps < π
    freqs = sfft.rfftfreq(n, 1 / setup["fs"])
    w = np.interp(freqs, setup["freqs"], setup["weights"], left=0.0, right=0.0) * freqs ** 2
    k = np.flatnonzero(w > 0)
    tg = -np.gradient(np.unwrap(np.angle(sfft.rfft(template, n)[k])), 2 * np.pi * freqs[k])
    return float(np.sum(w[k] * tg) / np.sum(w[k]))


def stretch_shifts(template, fs, band, locate_kw, pre, seg_len, whiten_hz, stretches):
    """This estimator's arrival shift (s) for the chirp received stretched by ``1 + ε`` about its start, for
    each ε of ``stretches`` (each realised exactly by band-limited resampling: returns the ε realised too).
    Small ε: β ε (:func:`drift_bias`); a source moving at ~1 m/s (ε ~ 3e-3) is beyond the linear range.
    Returns (shifts (n,), stretches realised (n,))."""
    n = len(template)
    smallest = min(abs(d) for d in stretches if d) if any(stretches) else 1e-3
    pad = sfft.next_fast_len(max(seg_len + 2 * pre, int(np.ceil(1.0 / smallest))))
    setup = spectra_setup(template, fs, band, seg_len, whiten_hz)
    shifts, real = [], []
    for d in stretches:
        k = int(round(d * pad)) or (0 if d == 0 else (1 if d > 0 else -1))
        dd = k / pad  # stretch realisable exactly by resampling pad → pad + k samples
        buf = np.zeros(pad)
        buf[pre : pre + n] = template
        y = fourier_resample(buf, pad + k)[:seg_len] if k else buf[:seg_len]  # y[i] = buf(i / (1 + dd))
        c = segment_spectra(y[None, :], np.zeros(1, int), setup)
        res = locate(c, setup, **locate_kw)
        shifts.append(res["tau"][0, 0] - pre * (1 + dd) / fs)
        real.append(dd)
    return np.asarray(shifts), np.asarray(real)
