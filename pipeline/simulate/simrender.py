"""The room simulator's audio: every emission rendered on every array's clock and streamed to the WAVs.

Memory is bounded by one emission's RIRs and segments plus the not-yet-final part of each recording
(about the longest segment): sessions of any length render in the same memory. Each recording is written
as float32 while it is rendered, then converted to the requested subtype (and scaled down if anything
would clip), block by block.
"""
from __future__ import annotations

import math
import os
from functools import partial
from pathlib import Path

import numpy as np

from calib.geometry import local_time
from calib.pipeline.simulate import acoustics as ac
from calib.pipeline.simulate import clocks
from calib.pipeline.simulate import motion, polyroom
from calib.pipeline.simulate import render as rd
from calib.pipeline.simulate.sounds import (BlockWhite, CoherentPink, RowMajorWhite, burst_params, burst_signal, chirp_power,
                     chirp_signal, hum, noise_params, noise_signal, speech_params, speech_signal)

TARGET_PEAK = 0.25   # the largest direct-path amplitude at any mic
CLIP = 0.95          # recordings are scaled down if any sample would exceed this


def _rng(seed, *purpose):
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(purpose)))


# ----------------------------------------------------------------------------------------------- levels
def direct_amplitudes(sc):
    """Per array (K, M) direct-path amplitudes at 0 dB emission: 1/d, times (``bands`` model) the
    speaker's gain towards the mic and the array's direct-path attenuation."""
    out = []
    for a in sc["arrays"]:
        d = np.linalg.norm(sc["sources"][:, None] - a["mics_room"][None], axis=2)
        amp = 1.0 / d
        if sc["model"] == "bands":
            u = (a["mics_room"][None] - sc["sources"][:, None]) / d[..., None]        # (K, M, 3)
            if sc["directivity"] != "omni":
                amp = amp * np.stack([ac.directivity_gain(sc["directivity"], ax, uj, sc["rear_floor_db"])
                                      for ax, uj in zip(sc["source_axis"], u)])
            amp = amp * 10 ** (a["direct_db"] / 20)
        out.append(amp)
    return out


def noise_levels(sc):
    """Global gain and noise standard deviations (before any rescaling): a dict.

    P = mean over arrays, mics and events of the direct-path chirp power at the mic (emission levels of
    ``event_level_db`` not included); white self-noise, diffuse noise and hum are set re. P by their SNRs.
    """
    direct = np.concatenate([x.ravel() for x in direct_amplitudes(sc)])
    gain = TARGET_PEAK / direct.max()
    p_chirp = chirp_power(sc["chirp"])
    p = float(np.mean((gain * direct) ** 2) * p_chirp)

    def std(snr):
        return math.sqrt(p / 10 ** (snr / 10)) if math.isfinite(snr) else 0.0
    return {"gain": gain, "p_chirp": p_chirp, "p_direct": p, "sigma": std(sc["snr"]),
            "sigma_diff": std(sc["diffuse_snr"]), "hum_std": std(sc["hum_snr"])}


# ----------------------------------------------------------------------------------------------- emitters
def emitters(sc, lv):
    """Every emission (chirps, then interferers) as a dict: kind, index, pos, t_start, dur, wave, level, axis."""
    ch = sc["chirp"]
    out = []
    traj = sc.get("trajectory")
    for j, s in enumerate(sc["sources"]):
        axis = sc["source_axis"][j] if sc["model"] == "bands" and sc["directivity"] != "omni" else None
        e = {"kind": "chirp", "index": j, "pos": s, "t_start": sc["t_emit"][j], "dur": ch["duration"],
             "wave": lambda u: chirp_signal(u, ch), "axis": axis,
             "level": lv["gain"] * 10 ** (sc["event_level_db"][j] / 20)}
        if traj is not None:               # moving speaker: images at the sweep's middle, early paths exact
            e |= {"pos": traj(e["t_start"] + e["dur"] / 2), "trajectory": traj}
        out.append(e)
    for k, it in enumerate(sc["interferers"]):
        if it["kind"] == "speech":
            prm = speech_params(sc["seed"], k, it["duration"], it["f0"], sc["fs"])

            wave = partial(speech_signal, duration=it["duration"], prm=prm)
        elif it["kind"] == "noise":
            freqs, amps, phases = noise_params(sc["seed"], k, it["f_lo"], it["f_hi"])
            wave = partial(noise_signal, duration=it["duration"], freqs=freqs, amps=amps, phases=phases)
        else:
            freqs, phases = burst_params(sc["seed"], k, it["f_lo"], it["f_hi"])
            wave = partial(burst_signal, duration=it["duration"], freqs=freqs, phases=phases)
        out.append({"kind": "interferer", "index": k, "pos": it["position"], "t_start": it["t_start"],
                    "dur": it["duration"], "wave": wave, "axis": None,
                    "level": lv["gain"] * math.sqrt(lv["p_chirp"]) * 10 ** (it["level_db"] / 20)})
    return out


def _attach_images(sc, em, flat, lo, hi):
    """Image sources of emitters ``em[lo:hi]`` (computed just before use: bounded memory)."""
    c = sc["speed_of_sound"]
    mics = np.concatenate([a["mics_room"] for a in sc["arrays"]])
    for e in em[lo:hi]:
        if sc["model"] == "flat":
            e["images"] = rd.pra_images(sc, *flat, e["pos"])
        elif sc.get("geometry") is not None:
            e["images"] = _poly_images(sc, e)
        else:
            # every image that can arrive within mixing_time of the direct path at any mic (+10 cm margin)
            reach = 2 * np.linalg.norm(mics - e["pos"], axis=1).max() + c * sc["mixing_time"] + 0.1
            e["images"] = ac.shoebox_images(np.asarray(e["pos"], float), sc["room_dim"], e["pos"], reach)
            if "trajectory" in e:           # the images' affine maps p_k(s) = M_k s + b_k (mirror signs)
                e["images"]["M"] = np.stack([np.diag(np.where(f, -1.0, 1.0)) for f in e["images"]["flip"]])
        if sc["model"] == "bands":
            e["diffuse_gain"] = (ac.mean_power_gain(sc["directivity"], sc["rear_floor_db"])
                                 if e["axis"] is not None else 1.0)


def _poly_images(sc, e):
    """Image sources of a polygonal room / a room with obstacles, with their visibility per mic set."""
    geo = sc["geometry"]
    tree = polyroom.image_tree(geo, np.asarray(e["pos"], float), sc["image_order"])
    return {**tree, "tree": True, "path_gain": lambda mics: polyroom.path_gains(geo, tree, mics)}


def _tail_length(sc):
    return float(np.max(sc["acoustic"]["rt60_bands"])) if sc["model"] == "bands" and sc["rt60"] > 0 else 0.0


def recording_ends(sc, em, flat):
    """Samples per array: from local time 0 to the last chirp's reverberation + ``tail`` (+ FDL)."""
    c, dur, t0 = sc["speed_of_sound"], sc["chirp"]["duration"], sc["t_emit"][0]
    chirps = [e for e in em if e["kind"] == "chirp"]
    last = np.zeros(len(sc["arrays"]))
    for n, e in enumerate(chirps):
        if sc["model"] == "flat":
            _attach_images(sc, chirps, flat, n, n + 1)
            images = e.pop("images")
            reach = [rd.flat_reach(images, a, c, sc["rt60"]) for a in sc["arrays"]]
        else:
            reach = [np.linalg.norm(a["mics_room"] - e["pos"], axis=1).max() / c + sc["mixing_time"]
                     + _tail_length(sc) for a in sc["arrays"]]
        for i, a in enumerate(sc["arrays"]):
            last[i] = max(last[i], clocks.local(a, e["t_start"] + reach[i] + dur, t0))
    return [int(math.ceil((x + sc["tail"]) * a["fs"])) + rd.FDL for x, a in zip(last, sc["arrays"])]


# ----------------------------------------------------------------------------------------------- noise
def _finisher(sc, i, a, n, lv):
    """finish(a, b, block) for array ``i``: diffuse noise, mic gains, self-noise and hum of samples [a, b)."""
    M, seed, fs = len(a["mics"]), sc["seed"], a["fs"]
    wide = math.sqrt(fs / sc["fs"])     # a faster recorder: same noise density in the chirp's band
    white = (RowMajorWhite(_rng(seed, 20 + 2 * i), M, n) if sc["model"] == "flat"
             else BlockWhite(seed, 40 + i, M)) if lv["sigma"] > 0 else None
    pink = CoherentPink(_rng(seed, 21 + 2 * i), a["mics_room"], fs, sc["speed_of_sound"]) \
        if lv["sigma_diff"] > 0 else None
    gains = 10 ** (a["mic_gain_db"] / 20)
    phases = _rng(seed, 60 + i).uniform(0, 2 * np.pi, sc["hum_harmonics"])

    def finish(lo, hi, block):
        if pink is not None:
            block += lv["sigma_diff"] * pink.get(lo, hi)
        if np.any(gains != 1.0):
            block *= gains[:, None]
        if white is not None:
            block += lv["sigma"] * wide * white.get(lo, hi)
        if lv["hum_std"] > 0:
            block += lv["hum_std"] * hum(lo, hi, fs, sc["hum_freq"], sc["hum_harmonics"], phases)[None]
        return block
    return finish


# ----------------------------------------------------------------------------------------------- render
def _prepare_arrays(sc, delay):
    """Arrays with the fixed RIR length of the ``bands`` model (longest direct path + mixing + tail)."""
    c = sc["speed_of_sound"]
    pos = np.concatenate([sc["sources"], np.array([it["position"] for it in sc["interferers"]]).reshape(-1, 3)])
    out = []
    for a in sc["arrays"]:
        a = dict(a)
        fsp = a["fs"] * (1 + a["drift"])
        dmax = np.linalg.norm(pos[:, None] - a["mics_room"][None], axis=2).max()
        a["rir_length"] = int(math.ceil((dmax / c + sc["mixing_time"] + _tail_length(sc)) * fsp)) \
            + rd.PAD + rd.FDL + delay
        out.append(a)
    return out


def _rir_function(sc, e, a, delay, exclude=None):
    if sc["model"] == "flat":
        return lambda fsp: rd.flat_rir(e["images"], a, fsp, sc["speed_of_sound"], sc["rt60"])
    rng = _rng(sc["seed"], 30, 0 if e["kind"] == "chirp" else 1, e["index"], a["index"])
    return lambda fsp: rd.band_rir(e, a, fsp, sc, delay, rng, exclude)


def _segment(sc, e, a, delay):
    """One emission at array ``a``: (first sample, (M, n) samples); a moving chirp's early paths rendered
    with the exact time-varying delay (:mod:`.motion`), the rest from the RIR at the sweep's middle."""
    fs, t0 = a["fs"], sc["t_emit"][0]
    if "trajectory" not in e:
        return rd.segment(e["wave"], e["t_start"], e["dur"], _rir_function(sc, e, a, delay),
                          a, fs, t0, delay, e["level"], local_time)
    fsp = fs * (1 + a["drift"])
    paths = rd.band_paths(e, a, fsp, sc)
    early = motion.early_mask(paths, fsp)
    start, seg = rd.segment(e["wave"], e["t_start"], e["dur"], _rir_function(sc, e, a, delay, early),
                            a, fs, t0, delay, e["level"], local_time)
    vis = None
    if "tree" in e["images"]:
        geo, traj = sc["geometry"], e["trajectory"]

        def vis(times):
            return np.stack([polyroom.path_gains(geo, e["images"], a["mics_room"],
                                                 polyroom.moved(e["images"], traj(t)), only=early) for t in times])
    lo, part = motion.early_part(e, a, paths, early, sc, t0, e["level"], vis)
    first = min(start, lo)
    out = np.zeros((seg.shape[0], max(start + seg.shape[1], lo + part.shape[1]) - first))
    out[:, start - first:start - first + seg.shape[1]] += seg
    out[:, lo - first:lo - first + part.shape[1]] += part
    return first, out


def render_session(sc, tmp, flat, progress=None, zero_peak=None):
    """Write ``tmp/<array>.wav`` for the normalised scenario ``sc``; return what the manifest reports.

    flat : (energy absorption, ISM order) of the ``flat`` model; progress : optional callback
    ``progress(done, total, message)``; zero_peak : function(path) that normalises a WAV's PEAK chunk.
    """
    delay = rd.builder_delay()
    lv = noise_levels(sc)
    em = sorted(emitters(sc, lv), key=lambda e: e["t_start"])
    ends = recording_ends(sc, em, flat)
    arrays = _prepare_arrays(sc, delay)
    tmp = Path(tmp)
    tracks = [rd.Track(tmp / f".{a['name']}.f32.wav", a["fs"], len(a["mics"]), _finisher(sc, i, a, n, lv))
              for i, (a, n) in enumerate(zip(arrays, ends))]
    for n in range(len(em)):
        _attach_images(sc, em, flat, n, n + 1)
        e = em[n]
        for a, tr in zip(arrays, tracks):
            start, seg = _segment(sc, e, a, delay)
            tr.flush(max(start, 0))
            tr.add(start, seg)
        e.pop("images")
        if progress:
            progress(n + 1, len(em) + 1, "rendering")
    for tr, end in zip(tracks, ends):
        tr.close(end)
    peak = max(tr.peak for tr in tracks)
    rescale = CLIP / peak if peak > CLIP else 1.0
    for a in arrays:
        src, dst = tmp / f".{a['name']}.f32.wav", tmp / f"{a['name']}.wav"
        if sc["subtype"] == "FLOAT" and rescale == 1.0:
            os.replace(src, dst)
            zero_peak(dst)
        else:
            rd.finalise_wav(src, dst, a["fs"], sc["subtype"], rescale, zero_peak)
            src.unlink()
    if progress:
        progress(len(em) + 1, len(em) + 1, "written")
    return {"levels": lv, "rescale": rescale, "ends": ends, "delay": delay}


def impulse_response(sc, event, array, flat=(None, None)):
    """Impulse response (M, L) from chirp ``event``'s speaker (its directivity and axis) to ``array``
    (indices), on that array's sample grid, unit emission (no global gain), and that grid's rate ``fsp``.
    Index ``n`` is ``n − delay`` samples after the emission (``delay = render.builder_delay()``).
    flat : (energy absorption, ISM order) for the ``flat`` model."""
    delay = rd.builder_delay()
    em = [e for e in emitters(sc, {"gain": 1.0, "p_chirp": 1.0}) if e["kind"] == "chirp"]
    a = _prepare_arrays(sc, delay)[array]
    _attach_images(sc, em, flat, event, event + 1)
    fsp = a["fs"] * (1 + a["drift"])
    return _rir_function(sc, em[event], a, delay)(fsp), fsp


# ----------------------------------------------------------------------------------------------- line of sight
LOS_COLS = ["event", "array", "los", "direct_db", "direct_minus_reflection_db", "cause", "los_fraction"]


def line_of_sight(sc):
    """Truth of the direct path per event and array (``bands`` model): a DataFrame of ``LOS_COLS``.

    At the array ORIGIN, the speaker at the sweep START (the event's truth position): ``los`` 1 when the
    direct path arrives unobstructed (no wall, obstacle or mount attenuation), ``direct_db`` its gain re.
    free field at 1 kHz (dB ≤ 0; empty when a wall blocks it), ``direct_minus_reflection_db`` the direct
    path's 1 kHz amplitude over the strongest reflection arriving within ``mixing_time`` (dB; empty when
    blocked: only reflections arrive), ``cause`` what attenuates or blocks it (``wall``, ``obstacle``,
    ``mount``, joined by ``+``; empty when clear), ``los_fraction`` the share of the sweep (moving speaker:
    ``motion.N_VIS_KNOTS`` instants) during which no wall blocks it.
    """
    import pandas as pd

    geo, traj = sc.get("geometry"), sc.get("trajectory")
    b1k = ac.BAND_CENTERS.index(ac.RT60_BAND)
    em = [e for e in emitters(sc, {"gain": 1.0, "p_chirp": 1.0}) if e["kind"] == "chirp"]
    rows = []
    for j, e in enumerate(em):
        e = {**e, "pos": sc["sources"][j]}
        e.pop("trajectory", None)
        _attach_images(sc, [e], None, 0, 1)
        knots = sc["t_emit"][j] + sc["chirp"]["duration"] * np.linspace(0, 1, motion.N_VIS_KNOTS)
        for a in sc["arrays"]:
            o = np.asarray(a["position"], float)
            g = polyroom.direct_gain(geo, sc["sources"][j], o[None])[0, b1k] if geo is not None else 1.0
            at = [traj(t) for t in knots] if traj is not None else [sc["sources"][j]]
            seen = [polyroom.direct_gain(geo, p, o[None])[0, b1k] > 0 if geo is not None else True for p in at]
            cause = ["wall"] if g == 0 else ["obstacle"] if g < 1 else []
            cause += ["mount"] if a["direct_db"] < 0 else []
            paths = rd.band_paths(e, {**a, "mics_room": o[None]}, a["fs"], sc)
            amp = paths["amp"][:, 0, b1k] / paths["dist"][:, 0]
            refl = np.max(np.where(np.isfinite(paths["taps"][:, 0]) & ~e["images"]["direct"], amp, 0.0))
            direct = float(amp[e["images"]["direct"]][0])
            rows.append({"event": j, "array": a["name"], "los": int(not cause),
                         "direct_db": 20 * np.log10(g) + a["direct_db"] if g > 0 else np.nan,
                         "direct_minus_reflection_db": 20 * np.log10(direct / refl) if direct > 0 and refl > 0
                         else np.nan, "cause": "+".join(cause), "los_fraction": float(np.mean(seen))})
    return pd.DataFrame(rows, columns=LOS_COLS)
