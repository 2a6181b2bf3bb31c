"""Rendering for the room simulator: RIRs on each array's drifting sample grid, and recordings written block
by block (bounded memory: one emission's segment and the not-yet-final part of each recording are held).

Two acoustic models (scenario key ``model``):

* ``flat`` — pyroomacoustics' image sources with one frequency-flat absorption (Sabine inversion), omni
  speaker, no air absorption; images kept up to RT60 after the direct path (the original simulator; its
  bytes are unchanged).
* ``bands`` — :mod:`calib.pipeline.simulate.acoustics`: octave-band wall materials and air absorption on the image
  sources up to ``mixing_time`` after the direct path, a stochastic late tail per band decaying at the
  band's Sabine RT60 and spatially coherent across the array (diffuse field), speaker directivity by
  emission direction, an optional per-array direct-path attenuation.
"""
from __future__ import annotations

import math

import numpy as np
import soundfile as sf
from scipy.fft import irfft, next_fast_len, rfft, rfftfreq

from calib.pipeline.simulate import acoustics as ac
from calib.pipeline.simulate import clocks

FDL = 81           # fractional-delay filter length (pyroomacoustics default)
LUT_GRAN = 512     # sinc look-up granularity of the RIR builder (pra default 20; finer = more exact delays)
N_THREADS = 2      # fixed so that the builder's summation order (hence every output byte) is reproducible
FDL_LATE = 21      # shorter filter for late reflections (> EARLY s after the direct path)
EARLY = 0.05       # s
PAD = FDL // 2 + 1  # samples added to every image delay so the builder never indexes before 0
TAIL_FADE = 0.002  # s, raised-cosine fade-in of the stochastic tail at the mixing time
WRAP_MARGIN = 0.02  # s of zero padding so the zero-phase band filters' pre-ringing never wraps around


# ----------------------------------------------------------------------------------------------- RIR builder
def build_rirs(delays, amps, length, early=np.inf, horizon=np.inf):
    """RIRs (n_mics, length) from image delays in SAMPLES (n_img, n_mics) and amplitudes (n_img, n_mics).

    pyroomacoustics' windowed-sinc builder takes times and an integer rate; we hand it delays already in
    the array's samples (rate 1) plus ``PAD`` so the filter never starts before index 0. Images arriving
    within ``early`` samples of the first one get the full ``FDL``-tap filter; later (weak, dense) ones a
    ``FDL_LATE``-tap one (< 1 % response error below fs/3); images beyond ``horizon`` samples after the
    first are dropped. NaN delays are skipped.
    """
    from pyroomacoustics import libroom

    out = np.zeros((delays.shape[1], length))
    for m in range(delays.shape[1]):
        d, a = delays[:, m], amps[:, m]
        ok = np.isfinite(d)
        d, a = d[ok], a[ok]
        if d.size == 0:
            continue
        rel = d - d.min()
        for fdl, sel in ((FDL, rel <= early), (FDL_LATE, (rel > early) & (rel <= horizon))):
            if sel.any():
                libroom.rir_builder(out[m], np.ascontiguousarray(d[sel] + PAD), np.ascontiguousarray(a[sel]),
                                    1, fdl, LUT_GRAN, N_THREADS)
    return out


def builder_delay():
    """Global delay (samples) of :func:`build_rirs`, measured: the peak of a lone image at an integer delay
    (for both filter lengths, which must agree)."""
    n0 = 3 * FDL
    found = set()
    for early in (np.inf, -1.0):
        h = build_rirs(np.array([[float(n0)]]), np.array([[1.0]]), 6 * FDL, early=early)[0]
        k = int(np.argmax(h))
        if not abs(h[k] - 1.0) < 1e-3 or np.max(np.abs(np.delete(h, k))) > 1e-3:
            raise RuntimeError("pyroomacoustics RIR builder: unexpected impulse shape")
        found.add(k - n0)
    if len(found) != 1:
        raise RuntimeError(f"pyroomacoustics RIR builder: filter lengths disagree on the delay {found}")
    return found.pop()


# ----------------------------------------------------------------------------------------------- flat model
def pra_images(sc, e_abs, order, position):
    """Image sources of one position (pyroomacoustics ISM, flat absorption): (images (3, n), damping (n,))."""
    import pyroomacoustics as pra

    room = pra.ShoeBox(sc["room_dim"].tolist(), fs=sc["fs"], materials=pra.Material(e_abs), max_order=order,
                       air_absorption=False, use_rand_ism=False)
    room.add_source(np.asarray(position, float))
    room.add_microphone_array(np.concatenate([a["mics_room"] for a in sc["arrays"]]).T)
    room.image_source_model()
    src = room.sources[0]
    vis = room.visibility[0].all(axis=0)   # a shoebox sees every image; kept in case that ever changes
    return src.images[:, vis], src.damping[0, vis]


def flat_rir(images, a, fsp, c, rt60):
    """RIRs (M, L) of the flat model for array ``a`` on its sample grid (rate ``fsp``)."""
    img, damp = images
    dist = np.linalg.norm(img[:, :, None] - a["mics_room"].T[:, None, :], axis=0)  # (n_img, M)
    taps = dist * (fsp / c)
    return build_rirs(taps, damp[:, None] / dist, int(math.ceil(taps.max())) + PAD + FDL,
                      early=EARLY * fsp, horizon=rt60 * fsp if rt60 > 0 else np.inf)


def flat_reach(images, a, c, rt60):
    """Propagation time (s) after which the flat model's RIR at array ``a`` has ended."""
    dist = np.linalg.norm(images[0][:, :, None] - a["mics_room"].T[:, None, :], axis=0)
    return dist.max() / c if rt60 == 0 else min(dist.max() / c, dist.min() / c + rt60)


# ----------------------------------------------------------------------------------------------- bands model
def band_paths(em, a, fsp, sc):
    """The early image paths of emitter ``em`` at array ``a`` (rate ``fsp``): a dict with ``taps`` (n, M)
    delays in samples (NaN: later than ``mixing_time`` after the direct path, or blocked), ``dist`` (n, M)
    m, ``amp`` (n, M, B) band amplitudes without the 1/distance spreading (wall reflections, speaker
    directivity, air absorption, occlusion of the direct path, walls and obstacles of a polygonal room),
    ``amp_open``, ``taps_open`` the same before walls and obstacles block or attenuate the paths, ``first``
    (the geometric direct path's delay, samples, blocked or not)."""
    ab, c = sc["acoustic"], sc["speed_of_sound"]
    img, mics = em["images"], a["mics_room"]
    dist = np.linalg.norm(img["pos"][:, None, :] - mics[None], axis=2)          # (n, M)
    taps = dist * (fsp / c)
    first = taps[img["direct"]].min()
    taps = np.where(taps <= first + sc["mixing_time"] * fsp, taps, np.nan)      # early part: images
    gain = np.ones_like(dist)
    if em["axis"] is not None:
        gain = ac.directivity_gain(sc["directivity"], em["axis"], ac.emission_directions(img, mics),
                                    sc["rear_floor_db"])
    gain[img["direct"]] *= 10 ** (a["direct_db"] / 20)
    amp = ac.image_band_amplitudes(img["hits"], ab["alpha"])[:, None, :] * gain[..., None] \
        * np.exp(-0.5 * ab["air"][None, None, :] * dist[..., None])                # (n, M, B)
    out = {"dist": dist, "amp_open": amp, "taps_open": taps, "first": first}
    if "tree" in img:                                  # polygonal room / obstacles: what actually arrives
        amp = amp * img["path_gain"](mics)
        taps = np.where(np.any(amp > 0, axis=2), taps, np.nan)
    return out | {"taps": taps, "amp": amp}


def band_rir(em, a, fsp, sc, delay, rng, exclude=None):
    """RIRs (M, L) of the ``bands`` model for emitter ``em`` at array ``a`` (rate ``fsp``).

    em : dict with ``images`` (:func:`acoustics.shoebox_images` or a ``polyroom`` tree), ``axis`` (3,)
        speaker axis or None.
    a : normalised array with ``mics_room`` and ``rir_length`` (samples, fixed per array), ``direct_db``.
    exclude : (n,) bool, images left out (a moving source renders them itself, :mod:`.motion`).
    """
    paths = band_paths(em, a, fsp, sc)
    taps, dist = paths["taps"], paths["dist"]
    if exclude is not None:
        taps = np.where(exclude[:, None], np.nan, taps)
    L = a["rir_length"]
    nfft = next_fast_len(L + int(WRAP_MARGIN * fsp))
    W = ac.band_weights(rfftfreq(nfft, 1 / fsp))
    H = np.zeros((len(a["mics_room"]), nfft // 2 + 1), complex)
    for b in range(len(ac.BAND_CENTERS)):
        H += W[b] * rfft(build_rirs(taps, paths["amp"][:, :, b] / dist, L), nfft, axis=1)
    if sc["rt60"] > 0:
        H += _tail_spectrum(a, fsp, sc, paths["first"], delay, rng, nfft, W, em["diffuse_gain"])
    return irfft(H, nfft, axis=1)[:, :L]


def _tail_spectrum(a, fsp, sc, first, delay, rng, nfft, W, diffuse_gain):
    """Spectrum (M, F) of the stochastic late tail from ``mixing_time`` after the direct path on."""
    ab, c = sc["acoustic"], sc["speed_of_sound"]
    L, M = a["rir_length"], len(a["mics_room"])
    n = np.arange(L)
    t = (n - delay) / fsp                         # propagation time of RIR index n
    t0 = (first) / fsp + sc["mixing_time"]
    fade = np.clip((t - t0) / TAIL_FADE, 0, 1)
    fade = 0.5 - 0.5 * np.cos(np.pi * fade)
    env = ac.tail_envelopes(np.maximum(t, 0), ab["rt60_bands"], ab["volume"], c, fsp, diffuse_gain) * fade
    T = np.zeros((M, nfft // 2 + 1), complex)
    for b in range(len(ac.BAND_CENTERS)):     # independent noise per band, power-complementary weights
        T += np.sqrt(W[b]) * rfft(rng.standard_normal((M, L)) * env[b], nfft, axis=1)
    return np.einsum("fmn,nf->mf", ac.diffuse_coherence_mix(a["mics_room"], rfftfreq(nfft, 1 / fsp), c), T)


# ----------------------------------------------------------------------------------------------- segments
def segment(wave, t_start, dur, rir, a, fs, t0, delay, level, local_time):
    """One emission at array ``a``: (first sample index, (M, n) samples) of ``rir ⊗ wave`` on its clock.

    ``rir`` is a function of the array's true-time sample rate ``fsp`` returning (M, L) taps.
    """
    from scipy.signal import fftconvolve  # (scipy.signal is slow to import: loaded when rendering)

    if a.get("clock") is not None:                   # a faulty clock (steps, drift terms): pipeline.simulate.clocks
        fsp, nu = fs * clocks.rate(a, t_start), fs * clocks.local(a, t_start, t0)
    else:
        fsp = fs * (1.0 + a["drift"])                    # true-time rate of this array's samples
        nu = fs * local_time(t_start, a["tau"], a["drift"], t0)   # emission instant in this array's samples
    n0 = int(math.floor(nu))
    frac = nu - n0
    p = np.arange(int(math.ceil(dur * fsp + frac)) + 2)
    x = wave((p - frac) / fsp)                       # the emitted wave on this array's sample grid
    seg = fftconvolve(rir(fsp), x[None, :], axes=1) * level
    return n0 - delay, seg                           # conv index `delay` ↔ emission instant


# ----------------------------------------------------------------------------------------------- writing
class Track:
    """One array's recording, written to a float32 WAV block by block.

    ``add`` accumulates emission segments; ``flush(upto)`` finalises samples before ``upto`` (no later
    segment may start before it): ``finish(a, b, block)`` adds noise etc., then the block is written.
    """

    def __init__(self, path, fs, n_ch, finish):
        self.file = sf.SoundFile(path, "w", fs, n_ch, subtype="FLOAT", format="WAV")
        self.buf = np.zeros((n_ch, 0))
        self.base = 0
        self.finish = finish
        self.peak = 0.0

    def _cover(self, end):
        if end > self.base + self.buf.shape[1]:
            self.buf = np.pad(self.buf, ((0, 0), (0, end - self.base - self.buf.shape[1])))

    def add(self, start, seg):
        if start < 0:                                 # before the recording started: clipped
            seg, start = seg[:, -start:], 0
        if start < self.base:
            raise RuntimeError("Track.add: segment starts before the written part")
        if seg.shape[1] == 0:
            return
        self._cover(start + seg.shape[1])
        self.buf[:, start - self.base:start - self.base + seg.shape[1]] += seg

    def flush(self, upto, block=1 << 16):
        while upto > self.base:
            b = min(upto, self.base + block)
            self._cover(b)
            out = self.finish(self.base, b, self.buf[:, :b - self.base].copy())
            self.peak = max(self.peak, float(np.max(np.abs(out))) if out.size else 0.0)
            self.file.write(out.T.astype(np.float32))
            self.buf = self.buf[:, b - self.base:]
            self.base = b

    def close(self, end):
        self.flush(end)
        self.file.close()


def finalise_wav(src, dst, fs, subtype, rescale, write_wav, block=1 << 16):
    """Copy the float32 ``src`` to ``dst`` in ``subtype``, scaled by ``rescale``, block by block."""
    with sf.SoundFile(src) as f, sf.SoundFile(dst, "w", fs, f.channels, subtype=subtype, format="WAV") as g:
        for x in f.blocks(blocksize=block, dtype="float32", always_2d=True):
            g.write(x if rescale == 1.0 else (x.astype(np.float64) * rescale).astype(np.float32))
    write_wav(dst)
