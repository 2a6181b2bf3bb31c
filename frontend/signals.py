"""Audio input and the emitted chirp: reading array WAVs, the matched-filter template, band weights.

Conventions: a multichannel recording is an ``(M, N)`` float32 array (channel-major), sampled at ``fs``;
sample ``n`` is taken at local time ``n / fs`` of the array's clock. The template is the emitted chirp
sampled at the array's rate, starting at sample 0 (its time origin defines "the chirp's start").
"""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import scipy.fft as sfft
import scipy.signal as ss
import soundfile as sf

from calib.errors import InputError


def read_header(array):
    """Check one array's audio file against the session without reading the samples.

    array : dict from ``pipeline.session.read_session`` (``name``, ``wav``, ``mics`` (M, 3)).
    Returns the ``soundfile.info`` of the file. Raises :class:`InputError` naming the file for an
    unreadable file, a channel count that is not the number of mics, or an empty file.
    """
    path, n_mics = array["wav"], len(array["mics"])
    try:
        info = sf.info(str(path))
    except Exception as exc:  # libsndfile reports format problems in many ways
        raise InputError(f"{path}: cannot read audio ({_first_line(exc)})") from None
    if info.channels != n_mics:
        what = "a mono file" if info.channels == 1 else f"{info.channels} channels"
        raise InputError(f"{path}: {what}, but array {array['name']!r} has {n_mics} mics in session.toml")
    if info.frames == 0:
        raise InputError(f"{path}: no audio samples")
    return info


def read_array_audio(array):
    """Read one array's recording, checked as :func:`read_header` does.

    Returns
    -------
    x : (M, N) float32 ndarray (a transposed view of the sample-major file data).
    fs : int, sample rate (Hz).
    """
    read_header(array)
    path = array["wav"]
    try:
        data, fs = sf.read(str(path), dtype="float32", always_2d=True)
    except Exception as exc:
        raise InputError(f"{path}: cannot read audio ({_first_line(exc)})") from None
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: contains non-finite samples")
    return data.T, int(fs)  # a view: slicing events out of it is cheaper than transposing everything


def _first_line(exc):
    msg = str(exc).strip().splitlines()
    return msg[0] if msg else type(exc).__name__


SWEEP_KINDS = ("linear", "exponential")


def sweep(u, f0, f1, duration, fade=0.0, kind="linear"):
    """The emitted sweep at times ``u`` (s since its start), unit amplitude, 0 outside ``[0, duration]``.

    kind : "linear", phase ``2π (f0 u + (f1 − f0) u² / (2 T))``; or "exponential" (log sweep, Farina),
        phase ``2π f0 T / ln(f1/f0) · ((f1/f0)^(u/T) − 1)``, instantaneous frequency ``f0 (f1/f0)^(u/T)``.
    fade : raised-cosine fades of ``fade`` s at both ends (``½(1 − cos(π u / fade))`` on the first ``fade``
        s, mirrored on the last).

    The one definition of the chirp: the simulators render it, the frontend's template samples it.
    """
    u = np.asarray(u, float)
    if kind == "linear":
        phase = f0 * u + 0.5 * (f1 - f0) / duration * u * u
    elif kind == "exponential":
        ratio = f1 / f0
        phase = f0 * duration / np.log(ratio) * (np.power(ratio, u / duration) - 1.0)
    else:
        raise ValueError(f"unknown sweep kind {kind!r} (expected one of {SWEEP_KINDS})")
    s = np.sin(2 * np.pi * phase)
    if fade > 0:
        edge = np.minimum(u, duration - u)
        s = s * np.where(edge < fade, 0.5 * (1 - np.cos(np.pi * np.clip(edge, 0, fade) / fade)), 1.0)
    return np.where((u >= 0) & (u < duration), s, 0.0)


def resample(x, fs_from, fs_to):
    """Band-limited rational resampling of a 1-D signal (polyphase)."""
    if fs_from == fs_to:
        return np.asarray(x, float)
    r = Fraction(fs_to / fs_from).limit_denominator(1000)
    return ss.resample_poly(np.asarray(x, float), r.numerator, r.denominator)


def chirp_template(chirp, fs):
    """The emitted signal sampled at ``fs``, starting at sample 0.

    chirp : the session's chirp dict (f0, f1, duration, kind, reference). A reference WAV (mono) wins over the
        synthesised sweep; it is resampled to ``fs`` when its rate differs.

    Returns (L,) float64 ndarray.
    """
    ref = chirp.get("reference")
    if ref is not None:
        try:
            data, fs_ref = sf.read(str(ref), dtype="float64", always_2d=True)
        except Exception as exc:
            raise InputError(f"{ref}: cannot read audio ({_first_line(exc)})") from None
        if data.shape[1] != 1:
            raise InputError(f"{ref}: chirp reference must be mono, has {data.shape[1]} channels")
        s = resample(data[:, 0], fs_ref, fs)
        if not np.any(s):
            raise InputError(f"{ref}: chirp reference is silent")
        return s
    n = int(math.ceil(chirp["duration"] * fs))
    return sweep(np.arange(n) / fs, chirp["f0"], chirp["f1"], chirp["duration"], chirp.get("fade", 0.0),
                 chirp.get("kind", "linear"))


def chirp_band(chirp, template, fs):
    """(f_lo, f_hi) in Hz: the sweep's band, or where a reference WAV holds 99% of its energy."""
    if chirp.get("f0") is not None and chirp.get("f1") is not None:
        lo, hi = sorted((chirp["f0"], chirp["f1"]))
        return float(lo), float(min(hi, 0.49 * fs))
    p = np.abs(sfft.rfft(template)) ** 2
    f = sfft.rfftfreq(len(template), 1 / fs)
    c = np.cumsum(p) / p.sum()
    return float(f[np.searchsorted(c, 0.005)]), float(f[min(np.searchsorted(c, 0.995), len(f) - 1)])


def band_weights(freqs, band, taper=0.2):
    """Tukey-shaped weights over ``band`` (Hz): 1 inside, cosine roll-off over ``taper`` of its width at
    each edge, 0 outside. Band-limiting the GCC to the chirp's band keeps out-of-band noise out; the smooth
    edges keep the correlation's sidelobes low.

    freqs : (F,) Hz. Returns (F,) float64.
    """
    lo, hi = band
    w = np.zeros(len(freqs))
    edge = taper * (hi - lo)
    inside = (freqs >= lo) & (freqs <= hi)
    w[inside] = 1.0
    if edge > 0:
        a = inside & (freqs < lo + edge)
        w[a] = 0.5 - 0.5 * np.cos(np.pi * (freqs[a] - lo) / edge)
        b = inside & (freqs > hi - edge)
        w[b] = 0.5 - 0.5 * np.cos(np.pi * (hi - freqs[b]) / edge)
    return w
