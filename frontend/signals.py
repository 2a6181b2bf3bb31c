"""Audio input and the emitted chirp: reading array WAVs, the matched-filter template, band weights.

Conventions: a multichannel recording is an ``(M, N)`` float32 array (channel-major), sampled at ``fs``;
sample ``n`` is taken at local time ``n / fs`` of the array's clock. The template is the emitted chirp
sampled at the array's rate, starting at sample 0 (its time origin defines "the chirp's start").
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import scipy.fft as sfft
import soundfile as sf

from calib.errors import InputError


def audio_files(array):
    """The audio files of an array: ``array["files"]`` (one mono file per mic, in the order of ``mics``), or
    its one ``wav``."""
    return tuple(array.get("files") or (array["wav"],))


@dataclass(frozen=True)
class PerMicInfo:
    """The header of an array recorded as one mono file per mic (:func:`read_header`): the files' common
    rate, length and sample format; ``channels`` = the number of mics. (Also a header whose rate the session
    declares.)"""
    samplerate: int
    channels: int
    frames: int
    subtype: str
    format: str

    @property
    def duration(self):
        return self.frames / self.samplerate


def _info(path):
    try:
        info = sf.info(str(path))
    except Exception as exc:  # libsndfile reports format problems in many ways
        raise InputError(f"{path}: cannot read audio ({_first_line(exc)})") from None
    if info.frames == 0:
        raise InputError(f"{path}: no audio samples")
    return info


def read_header(array):
    """Check one array's audio against the session without reading the samples.

    array : dict from ``pipeline.formats.session.read_session`` (``name``, ``wav``, ``mics`` (M, 3), optional
    ``channels``: the file's channel of each mic, counted from 0; optional ``files``: one mono file per mic).
    Returns the ``soundfile.info`` of the file (a :class:`PerMicInfo` for one file per mic). Raises
    :class:`InputError` naming the file for an unreadable or empty file, a channel count that is not the
    number of mics (without a channel map), a mapped channel the file lacks, or per-mic files that differ in
    rate or length. An array's ``sample_rate`` (session.toml: the true nominal rate of a board whose header
    is wrong) replaces the header's rate.
    """
    info = _file_header(array)
    rate = array.get("sample_rate")
    if rate is None:
        return info
    # the board's true nominal rate declared in session.toml (its WAV header is wrong): every stage takes the
    # samples at this rate (local time n / rate)
    return PerMicInfo(int(rate), int(info.channels), int(info.frames), info.subtype, info.format)


def _file_header(array):
    """:func:`read_header` as the files state it."""
    files, n_mics = audio_files(array), len(array["mics"])
    if len(files) > 1:
        return _per_mic_header(array, files)
    path, sel = files[0], array.get("channels")
    info = _info(path)
    if sel is None and info.channels != n_mics:
        what = "a mono file" if info.channels == 1 else f"{info.channels} channels"
        raise InputError(f"{path}: {what}, but array {array['name']!r} has {n_mics} mics in session.toml "
                         "(a raw recording with other channels too: give 'channels', docs/formats.md)")
    if sel is not None and max(sel) >= info.channels:
        raise InputError(f"{path}: {info.channels} channel(s), but array {array['name']!r} maps a mic to channel "
                         f"{max(sel)} (channels are counted from 0)")
    return info


def _per_mic_header(array, files):
    """:func:`read_header` of one mono file per mic: all mono, one rate, one length."""
    infos = [_info(f) for f in files]
    first = infos[0]
    for f, info in zip(files, infos):
        if info.channels != 1:
            raise InputError(f"{f}: {info.channels} channels, but array {array['name']!r} lists one mono file "
                             "per mic")
        if info.samplerate != first.samplerate:
            raise InputError(f"{f}: {info.samplerate} Hz, but {files[0].name} has {first.samplerate} Hz "
                             f"(array {array['name']!r}: its files must share one rate)")
        if info.frames != first.frames:
            raise InputError(f"{f}: {info.frames} frames, but {files[0].name} has {first.frames} "
                             f"(array {array['name']!r}: its files must have one length)")
    return PerMicInfo(int(first.samplerate), len(files), int(first.frames), first.subtype, first.format)


# integer PCM subtypes read as integers (libsndfile's float conversion divides by the full scale)
_INTEGER_READ = {"PCM_S8": (np.int16, 32768.0), "PCM_U8": (np.int16, 32768.0), "PCM_16": (np.int16, 32768.0),
                 "PCM_24": (np.int32, 2.0**31), "PCM_32": (np.int32, 2.0**31)}


def _int_channel_sum(frames, scale=1.0, out=None, cols=None):
    """Sum over the channels ``cols`` (a channel map; default all) of (N, M) integer PCM frames in float32,
    times ``scale`` (the inverse full scale), into ``out`` if given: (N,) float32."""
    sel = frames if cols is None else frames[:, list(cols)]
    return np.multiply(sel.sum(axis=1, dtype=np.float32), np.float32(scale), out=out)


class ArrayAudio:
    """One array's recording, read on demand: memory is bounded by what is asked for, not the file's length.

    Behaves as the ``(M, N)`` float32 recording for slicing ``x[:, a:b]`` (any ``a < b``; samples outside
    the file are 0), which is all :func:`calib.frontend.timing.segment_spectra` and
    :func:`calib.frontend.detect.matched_envelope` use. Non-finite samples raise :class:`InputError`
    naming the file when they are read. Use as a context manager (or call :meth:`close`).

    array : dict from ``pipeline.formats.session.read_session`` (``name``, ``wav``, ``mics``, optional
    ``channels``, ``files``); checked with :func:`read_header` on opening. With a channel map, the
    recording is the mapped channels in the order of the mics (the other channels are never converted);
    with one file per mic, a :class:`_PerMicAudio` stacks the files.
    """

    def __new__(cls, array):
        if cls is ArrayAudio and len(audio_files(array)) > 1:
            return super().__new__(_PerMicAudio)
        return super().__new__(cls)

    def __init__(self, array):
        info = read_header(array)
        self.path = audio_files(array)[0]
        self.fs, self.file_channels, self.frames = int(info.samplerate), int(info.channels), int(info.frames)
        sel = array.get("channels")
        self._sel = None if sel is None else np.asarray(sel, int)  # file column of each mic, or None: all
        self._cols = range(self.file_channels) if sel is None else tuple(int(c) for c in sel)
        self.channels = len(self._cols)
        self._weights = np.zeros(self.file_channels, np.float32)  # 1 on the mics' columns: their sum
        self._weights[list(self._cols)] = 1.0
        self._int = _INTEGER_READ.get(info.subtype)  # (dtype, full scale) for integer PCM, else None
        self._file = None
        self._sum_buf = self._fill_buf = None

    @property
    def shape(self):
        """(M, N): channels, frames."""
        return (self.channels, self.frames)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def release(self):
        """Drop the reused read buffers: a recording waiting between two phases of work holds none of its
        audio in memory."""
        self._sum_buf = self._fill_buf = None

    def close(self):
        self._sum_buf = self._fill_buf = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def _handle(self):
        if self._file is None:
            try:
                self._file = sf.SoundFile(str(self.path))
            except Exception as exc:
                raise InputError(f"{self.path}: cannot read audio ({_first_line(exc)})") from None
        return self._file

    def segment(self, start, stop, channel_sum=False):
        """Samples ``start .. stop − 1`` (zeros outside the file).

        Returns (M, stop − start) float32 (a transposed view of sample-major data), or (stop − start,) the
        sum over channels if ``channel_sum`` (integer PCM is then summed before its conversion to float:
        a quarter of the memory traffic of reading floats; the same values up to float32 rounding).
        """
        start, stop = int(start), int(stop)
        n = max(stop - start, 0)
        a, b = max(start, 0), min(stop, self.frames)
        raw = self._int is not None
        dtype = self._int[0] if raw else np.float32
        if channel_sum:  # the frames are only summed: one buffer reused block after block (no page faults)
            out = self._buffer("_sum_buf", n, dtype)
            out[: max(a - start, 0)] = 0
            out[max(b - start, 0) :] = 0
        else:
            out = np.zeros((n, self.file_channels), dtype)
        if b > a:
            self._read_into(a, out[a - start : b - start])
        if raw and channel_sum:
            return _int_channel_sum(out, 1.0 / self._int[1], cols=self._cols)
        if raw:  # integer PCM read as such and scaled here: half the bytes, ~3x cheaper than libsndfile's floats
            return np.multiply(self._mics(out.T), np.float32(1.0 / self._int[1]), dtype=np.float32)
        if channel_sum:
            return out @ self._weights
        return self._mics(out.T)

    def _mics(self, rows):
        """The mics' rows of (file channels, n) data: all of them (a view), or a copy in the channel map's order."""
        return rows if self._sel is None else rows[self._sel]

    def fill_segment(self, out, start):
        """Write frames ``start .. start + n − 1`` (all inside the file) into ``out`` ((M, n) float32, e.g. a
        slice of a larger array): the values of ``x[:, start:start + n]`` without an intermediate copy
        (the sample-major frames come through one reused buffer)."""
        n, start = out.shape[-1], int(start)
        buf = self._buffer("_fill_buf", n, self._int[0] if self._int is not None else np.float32)
        self._read_into(start, buf)
        if self._int is not None:
            np.multiply(self._mics(buf.T), np.float32(1.0 / self._int[1]), out=out, dtype=np.float32)
        else:
            out[...] = self._mics(buf.T)

    def _read_into(self, first, out):
        """Read ``len(out)`` frames from frame ``first`` into ``out`` ((n, M), C-contiguous)."""
        f = self._handle()
        try:
            f.seek(first)
            got = f.read(len(out), dtype=out.dtype.name, always_2d=True, out=out)
        except Exception as exc:
            raise InputError(f"{self.path}: cannot read audio ({_first_line(exc)})") from None
        if len(got) != len(out):
            raise InputError(f"{self.path}: file ends after {first + len(got)} of {self.frames} frames")
        if out.dtype.kind == "f":
            self._check_finite(got)

    def _check_finite(self, samples):
        if not np.all(np.isfinite(samples)):
            raise InputError(f"{self.path}: contains non-finite samples")

    def _buffer(self, name, n, dtype):
        """An (n, M) ``dtype`` view of a buffer kept in attribute ``name`` and reused read after read."""
        buf = getattr(self, name)
        if buf is None or buf.shape[0] < n or buf.dtype != dtype:
            buf = np.empty((n, self.file_channels), dtype)
            setattr(self, name, buf)
        return buf[:n]

    def __getitem__(self, key):
        """``x[:, a:b]``: as :meth:`segment` (a view-like (M, b − a) float32 array)."""
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None) and isinstance(key[1], slice)
                and key[1].step in (None, 1)):
            raise TypeError("ArrayAudio supports x[:, a:b] only")
        a = 0 if key[1].start is None else key[1].start
        b = self.frames if key[1].stop is None else key[1].stop
        return self.segment(a, b)

    def channel_sum(self):
        """A (1, N) view whose slices are the sum over channels (read on demand)."""
        return _ChannelSum(self)


class _PerMicAudio(ArrayAudio):
    """An array recorded as one mono file per mic (``array["files"]``): an :class:`ArrayAudio` per file, stacked
    as the ``(M, N)`` recording (same interface; :func:`read_header` has checked one rate and one length)."""

    def __init__(self, array):
        info = read_header(array)
        files = audio_files(array)
        self.path = files[0]
        self.fs, self.channels, self.frames = int(info.samplerate), len(files), int(info.frames)
        self._parts = [ArrayAudio({"name": array["name"], "wav": f, "mics": array["mics"][k : k + 1]})
                       for k, f in enumerate(files)]

    def segment(self, start, stop, channel_sum=False):
        if channel_sum:
            parts = iter(self._parts)
            acc = next(parts).segment(start, stop, channel_sum=True).copy()
            for p in parts:
                acc += p.segment(start, stop, channel_sum=True)
            return acc
        return np.concatenate([p.segment(start, stop) for p in self._parts])

    def fill_segment(self, out, start):
        for k, p in enumerate(self._parts):
            p.fill_segment(out[k : k + 1], start)

    def release(self):
        for p in self._parts:
            p.release()

    def close(self):
        for p in self._parts:
            p.close()


class _ChannelSum:
    """The sum over an :class:`ArrayAudio`'s channels, sliceable as a (1, N) array."""

    def __init__(self, audio):
        self.audio = audio
        self.shape = (1, audio.frames)

    def __getitem__(self, key):
        a, b = key[1].start, key[1].stop
        return self.audio.segment(a, b, channel_sum=True)[None]


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


def fourier_resample(x, num):
    """``scipy.signal.resample(x, num)`` of a real 1-D signal, the same values: the signal as one period of a
    band-limited periodic signal, sampled at ``num`` points over that period (its spectrum truncated or
    zero-padded; an unpaired Nyquist bin halved or doubled as scipy does). Here because importing
    scipy.signal costs ~0.35 s of CPU, which every features run would pay for the drift bias β
    (timing.stretch_shifts). x : (N,) float; returns (num,) float64."""
    x = np.asarray(x, float)
    n_x = len(x)
    m = min(num, n_x)
    spec = sfft.rfft(x)[: m // 2 + 1]
    if m % 2 == 0 and num != n_x:   # the unpaired bin at m / 2
        spec[m // 2] *= 2 if num < n_x else 0.5
    return sfft.irfft(spec / (n_x / num), n=num, overwrite_x=True)


def resample(x, fs_from, fs_to):
    """Band-limited resampling of a 1-D signal from ``fs_from`` to ``fs_to`` (Hz, integers), zero outside it:
    its first ``ceil(N fs_to / fs_from)`` samples at the new rate. The signal, zero-padded to at least twice
    its length (so the periodic extension's copies stay apart) and to a whole number of the rates' common
    periods, is resampled by FFT (:func:`fourier_resample`: ideal band-limited interpolation, no filter's
    transition band or ripple). A reference chirp at another rate than an array's: scipy.signal's polyphase
    filter, which this replaces, cost ~0.35 s of CPU per run to import (the templates agree to ~1e-3 of the
    peak at the band's edge, their timing to far below a nanosecond)."""
    x = np.asarray(x, float)
    if fs_from == fs_to:
        return x
    r = Fraction(int(round(fs_to)), int(round(fs_from)))
    n_out = -(-len(x) * r.numerator // r.denominator)
    pad = -(-2 * len(x) // r.denominator) * r.denominator
    return fourier_resample(np.r_[x, np.zeros(pad - len(x))], pad * r.numerator // r.denominator)[:n_out]


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
        if not np.isfinite(data).all():
            raise InputError(f"{ref}: contains non-finite samples (NaN or inf)")
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
