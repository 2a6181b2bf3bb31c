"""Sounds of the room simulator: the chirp, interferers (tone bursts, speech-like) and noise generators.

Emitted sounds are analytic functions of the time ``u`` since their start, so every array can evaluate
them on its own drifting sample grid. Noise generators produce any block ``[a, b)`` of a recording on
demand (sequentially), deterministically for a seed, so a recording can be written block by block.
"""
from __future__ import annotations

import math

import numpy as np

from calib.frontend.signals import sweep

from calib.pipeline.simulate.acoustics import diffuse_coherence_mix

NOISE_BLOCK = 1 << 16       # samples per independently seeded block of white noise
PINK_PERIODS = (1 << 15) + 1, (1 << 15) - 1   # co-prime periods of the two summed pink-noise loops (samples)
SYLLABLE_RATE = 4.0         # Hz, syllables of the speech-like interferer
VOWELS = np.array([[700, 1220, 2600], [530, 1840, 2480], [270, 2290, 3010], [570, 840, 2410],
                   [300, 870, 2240]], float)   # formant frequencies F1-F3 (Hz) of a, e, i, o, u
FORMANT_BW = np.array([80.0, 100.0, 150.0])    # formant bandwidths, Hz


def chirp_signal(u, ch):
    """The scenario's chirp ``ch`` (f0, f1, duration, fade, kind) at times ``u`` (s since its start)."""
    return sweep(u, ch["f0"], ch["f1"], ch["duration"], ch["fade"], ch.get("kind", "linear"))


def chirp_power(chirp):
    """Mean of ``chirp_signal²`` over its duration (dimensionless, ≈ 0.5)."""
    u = np.linspace(0, chirp["duration"], 200_001)
    return float(np.mean(chirp_signal(u, chirp) ** 2))


def burst_params(seed, index, f_lo, f_hi, n_tones=48):
    """Random tone frequencies and phases (n_tones,) of interferer ``index`` (own random stream)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(100, index)))
    return rng.uniform(f_lo, f_hi, n_tones), rng.uniform(0, 2 * np.pi, n_tones)


def burst_signal(u, duration, freqs, phases):
    """An interferer: sum of tones with a Hann envelope over ``duration`` (s), unit power; 0 outside."""
    u = np.asarray(u, float)
    env = np.where((u >= 0) & (u <= duration), np.sin(np.pi * np.clip(u, 0, duration) / duration) ** 2, 0.0)
    s = np.zeros_like(u)
    for f, p in zip(freqs, phases):
        s += np.cos(2 * np.pi * f * u + p)
    # mean of env² over the burst is 3/8, mean of the tone sum² is n_tones / 2
    return env * s / np.sqrt(3 / 8 * len(freqs) / 2)


NOISE_TONES = 256     # random tones of a broadband noise burst (a fan, a vacuum cleaner, a trolley)
NOISE_FADE = 0.02     # s, raised-cosine on/off ramps of a noise burst


def noise_params(seed, index, f_lo, f_hi):
    """Random log-spaced frequencies, pink (1/√f) amplitudes and phases of noise burst ``index``."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(102, index)))
    f = np.exp(rng.uniform(np.log(f_lo), np.log(f_hi), NOISE_TONES))
    a = rng.rayleigh(1.0, NOISE_TONES)           # log-spaced tones already give 1/f power density
    return f, a / np.sqrt(np.sum(a ** 2) / 2), rng.uniform(0, 2 * np.pi, NOISE_TONES)


def noise_signal(u, duration, freqs, amps, phases):
    """Broadband noise burst: many random tones (pink), flat envelope with NOISE_FADE ramps, unit power."""
    u = np.asarray(u, float)
    edge = np.clip(np.minimum(u, duration - u), 0, None)
    fade = min(NOISE_FADE, duration / 2)
    env = np.where(edge < fade, 0.5 * (1 - np.cos(np.pi * edge / fade)), 1.0)
    s = np.zeros_like(u)
    for f, a, p in zip(freqs, amps, phases):
        s += a * np.cos(2 * np.pi * f * u + p)
    return np.where((u >= 0) & (u <= duration), env * s, 0.0)


def speech_params(seed, index, duration, f0, fs):
    """Random parameters of a speech-like interferer: per-syllable harmonic amplitudes (n_syl, H),
    harmonic phases (H,), pitch-vibrato phase. Harmonics stay below 0.45 fs at the highest pitch."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(101, index)))
    n_syl = max(1, int(math.ceil(duration * SYLLABLE_RATE)))
    n_h = max(1, min(60, int(0.45 * fs / (f0 * 1.1))))
    h = np.arange(1, n_h + 1) * f0
    amp = np.zeros((n_syl, n_h))
    for k in range(n_syl):
        formants = VOWELS[rng.integers(len(VOWELS))] * rng.uniform(0.9, 1.1)
        resp = sum(1 / np.sqrt(1 + ((h - F) / (B / 2)) ** 2) for F, B in zip(formants, FORMANT_BW))
        a = resp / np.sqrt(np.arange(1, n_h + 1))          # glottal source tilt (−3 dB/octave in amplitude)
        amp[k] = a / np.sqrt(np.sum(a ** 2) / 2) * rng.uniform(0.6, 1.0)
    return {"amp": amp, "phase": rng.uniform(0, 2 * np.pi, n_h), "vib": rng.uniform(0, 2 * np.pi), "f0": f0}


def speech_signal(u, duration, prm):
    """Speech-like sound: harmonics of a vibrato pitch, formant-shaped per syllable, syllable envelopes
    (sin² at ``SYLLABLE_RATE``); about unit power over ``duration``; 0 outside."""
    u = np.asarray(u, float)
    inside = (u >= 0) & (u <= duration)
    uc = np.clip(u, 0, duration)
    syl = np.minimum((uc * SYLLABLE_RATE).astype(int), len(prm["amp"]) - 1)
    env = np.sin(np.pi * uc * SYLLABLE_RATE) ** 2 / math.sqrt(3 / 8)
    vib_rate, vib_depth = 0.7, 0.08                      # Hz, relative pitch excursion
    phi = 2 * np.pi * prm["f0"] * (uc - vib_depth / (2 * np.pi * vib_rate)
                                   * np.cos(2 * np.pi * vib_rate * uc + prm["vib"]))
    s = np.zeros_like(u)
    for k in range(prm["amp"].shape[1]):
        s += prm["amp"][syl, k] * np.sin((k + 1) * phi + prm["phase"][k])
    return np.where(inside, env * s, 0.0)


# ----------------------------------------------------------------------------------------------- noise
class BlockWhite:
    """White N(0, 1) noise (M, ·), block ``j`` of ``NOISE_BLOCK`` samples drawn from its own seeded stream."""

    def __init__(self, seed, purpose, n_ch):
        self.seed, self.purpose, self.n_ch = seed, purpose, n_ch
        self._cache = (None, None)

    def _block(self, j):
        if self._cache[0] != j:
            rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(self.purpose, j)))
            self._cache = (j, rng.standard_normal((self.n_ch, NOISE_BLOCK)))
        return self._cache[1]

    def get(self, a, b):
        """Samples [a, b) (M, b − a)."""
        out = np.empty((self.n_ch, b - a))
        k = a
        while k < b:
            j, off = divmod(k, NOISE_BLOCK)
            n = min(b - k, NOISE_BLOCK - off)
            out[:, k - a:k - a + n] = self._block(j)[:, off:off + n]
            k += n
        return out


class RowMajorWhite:
    """Exactly ``rng.standard_normal((M, n))`` of one generator, produced sequentially in time blocks
    (one generator state per row, found by drawing through the preceding rows once)."""

    def __init__(self, rng, n_ch, n):
        self.gens = []
        chunk = 1 << 18
        for m in range(n_ch):
            g = np.random.default_rng()
            g.bit_generator.state = rng.bit_generator.state
            self.gens.append(g)
            left = n
            while left > 0 and m < n_ch - 1:
                rng.standard_normal(min(chunk, left))
                left -= min(chunk, left)
        self.pos = 0

    def get(self, a, b):
        """Samples [a, b) (M, b − a); calls must be consecutive (a = previous b)."""
        if a != self.pos:
            raise RuntimeError("RowMajorWhite: blocks must be requested in order")
        self.pos = b
        return np.stack([g.standard_normal(b - a) for g in self.gens])


class CoherentPink:
    """Pink (1/f power) noise with the spatial coherence of a spherically diffuse field across ``mics``
    (sinc(2 f d / c)), unit variance per mic. Two periodic loops of co-prime lengths are summed, so any
    block is available in O(block) time and the pattern repeats only after P1·P2 samples."""

    def __init__(self, rng, mics, fs, c):
        self.loops = [self._loop(rng, mics, fs, c, p) for p in PINK_PERIODS]

    @staticmethod
    def _loop(rng, mics, fs, c, period):
        spec = np.fft.rfft(rng.standard_normal((len(mics), period)), axis=1)
        f = np.fft.rfftfreq(period, 1 / fs)
        mix = diffuse_coherence_mix(np.asarray(mics, float), f, c)           # (F, M, M)
        spec = np.einsum("fmn,nf->mf", mix, spec)
        w = np.zeros_like(f)
        w[1:] = 1 / np.sqrt(f[1:])
        x = np.fft.irfft(spec * w, n=period, axis=1)
        return x / x.std(axis=1, keepdims=True) / math.sqrt(len(PINK_PERIODS))

    def get(self, a, b):
        out = np.zeros((self.loops[0].shape[0], b - a))
        for x in self.loops:
            idx = np.arange(a, b) % x.shape[1]
            out += x[:, idx]
        return out


def hum(a, b, fs, f_mains, n_harmonics, phases):
    """Mains hum at samples [a, b) (b − a,): Σ_h sin(2π h f t + φ_h) / h, normalised to unit power."""
    t = np.arange(a, b) / fs
    h = np.arange(1, n_harmonics + 1)
    s = (np.sin(2 * np.pi * f_mains * np.outer(t, h) + phases[:n_harmonics]) / h).sum(axis=1)
    return s / math.sqrt(np.sum(1 / h ** 2) / 2)
