"""Tools for before a recording: the chirp to play and its schedule, a session.toml, a session check.

- :func:`chirp_files` — the sweep (``calib.frontend.signals.sweep``) as a WAV to play from the robot, and an
  emission schedule (``event,t_emit``, jittered intervals) the robot follows and logs into events.csv.
- :func:`init_session` — a ``session.toml`` from the WAVs of a folder and a board model
  (:data:`calib.pipeline.formats.boards.BOARDS`), one multichannel WAV per array or one mono WAV per mic.
- :func:`check_session` — validates a session without estimating: one row per check (array, check, status,
  detail), so a user sees everything that is wrong at once.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf

from calib.errors import InputError
from calib.frontend.signals import sweep

from calib.pipeline.formats.boards import BOARDS
from calib.pipeline.formats.io import atomic_write_text
from calib.pipeline.formats.session import session_toml


MODELS = tuple(BOARDS) + ("custom",)
# planar arrays: DOAs are taken on the side of +z (the side the mics face); say so in session.toml
PLANAR_HEMISPHERE = [0.0, 0.0, 1.0]

# Chirp defaults and why (docs/cli.md `calib chirp`):
CHIRP_F0 = 500.0        # Hz: above most room modes, HVAC hum and footsteps; small speakers still radiate it
CHIRP_F1 = 4000.0       # Hz: below spatial aliasing of ~4 cm mic spacings (c / 2d ≈ 4.3 kHz), within 16 kHz rates
CHIRP_DURATION = 0.5    # s: time-bandwidth 1750 → ~32 dB matched-filter gain; short against robot motion
CHIRP_FADE = 0.005      # s: raised-cosine edges, no click (a broadband click would spoil the matched filter)
INTERVAL = 2.0          # s: longer than RT60 + the largest propagation delay + the chirp, so chirps never overlap
JITTER = 0.25           # ± fraction of the interval: irregular spacing makes the event association unambiguous


def chirp_signal(fs, f0=CHIRP_F0, f1=CHIRP_F1, duration=CHIRP_DURATION, fade=CHIRP_FADE, kind="linear"):
    """The sweep sampled at ``fs`` (L,) float64, peak 1 (the session's ``[chirp]`` signal)."""
    n = int(np.ceil(duration * fs))
    return sweep(np.arange(n) / fs, f0, f1, duration, fade, kind)


def emission_schedule(n_events, interval=INTERVAL, jitter=JITTER, start=1.0, seed=0):
    """Emission times (n,) s: ``start`` then intervals drawn uniformly in interval·(1 ± jitter)."""
    if n_events < 3:
        raise InputError("n_events must be at least 3 (the estimator needs 3 events or more)")
    if not (0 <= jitter < 1) or interval <= 0:
        raise InputError("interval must be > 0 and jitter in [0, 1)")
    rng = np.random.default_rng(seed)
    steps = interval * (1 + jitter * rng.uniform(-1, 1, n_events - 1))
    return start + np.concatenate([[0.0], np.cumsum(steps)])


def chirp_files(out_dir, *, fs=48000, n_events=30, interval=INTERVAL, jitter=JITTER, seed=0, f0=CHIRP_F0,
                f1=CHIRP_F1, duration=CHIRP_DURATION, fade=CHIRP_FADE, kind="linear", amplitude=0.5):
    """Write ``chirp.wav`` (mono, PCM_24), ``schedule.csv`` (event,t_emit) and ``chirp.toml`` (the [chirp] table
    for session.toml) into ``out_dir``. Returns {name: path}."""
    if duration >= interval * (1 - jitter):
        raise InputError(f"the chirp ({duration} s) must be shorter than the shortest interval "
                         f"({interval * (1 - jitter):.3g} s)")
    if max(f0, f1) >= 0.5 * fs:
        raise InputError(f"f1 = {max(f0, f1)} Hz is not below the Nyquist frequency of fs = {fs} Hz")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    x = amplitude * chirp_signal(fs, f0, f1, duration, fade, kind)
    tmp = out / ".chirp.wav.tmp"
    sf.write(str(tmp), x, int(fs), subtype="PCM_24", format="WAV")
    tmp.replace(out / "chirp.wav")
    t = emission_schedule(n_events, interval, jitter, seed=seed)
    atomic_write_text(out / "schedule.csv", pd.DataFrame({"event": np.arange(len(t)), "t_emit": t})
                      .to_csv(index=False, float_format="%.6f", lineterminator="\n"))
    atomic_write_text(out / "chirp.toml", "[chirp]\n" + "".join(
        f"{k} = {v!r}\n" for k, v in (("f0", float(f0)), ("f1", float(f1)), ("duration", float(duration)),
                                       ("fade", float(fade)), ("kind", kind), ("reference", "chirp.wav"))))
    return {"chirp": out / "chirp.wav", "schedule": out / "schedule.csv", "toml": out / "chirp.toml"}


def model_layout(model, channels, where):
    """(mics (M, 3), channel map or None) of ``model`` for a WAV of ``channels`` channels: a WAV of the mics
    only needs no map; one in the board's raw layout gets the board's map. custom: zeros to fill in."""
    if model == "custom":
        return np.zeros((channels, 3)), None
    if model not in BOARDS:
        raise InputError(f"unknown array model {model!r}: one of {', '.join(MODELS)}")
    b = BOARDS[model]
    if channels == len(b.mics):
        return b.mic_array(), None
    if channels == b.raw_channels:
        return b.mic_array(), list(b.channels)
    raise InputError(f"{where}: {channels} channels, but a {model} has {len(b.mics)} mics (raw layout: "
                     f"{b.raw_channels} channels); record the mics or the board's raw channels, or use --model custom")


LAYOUTS = ("array", "per-mic")
# one mono file per mic: <array>-<mic number>.wav (the seed paper's published audio: arr<i>-<m>.wav)
PER_MIC_NAME = re.compile(r"^(?P<array>.+)-(?P<mic>[0-9]+)\.wav$")


def _audio(path):
    try:
        return sf.info(str(path))
    except Exception as exc:
        raise InputError(f"{path}: cannot read audio ({str(exc).splitlines()[0]})") from None


def _group_per_mic(d, wavs):
    """{array name: [files in mic order]} of ``<array>-<mic>.wav`` files (each mono)."""
    groups = {}
    for w in wavs:
        m = PER_MIC_NAME.match(w.name)
        if m is None:
            raise InputError(f"{w}: not named <array>-<mic>.wav (--layout per-mic: one mono file per mic)")
        groups.setdefault(m["array"], []).append((int(m["mic"]), w))
    out = {}
    for name, items in sorted(groups.items()):
        nums = sorted(n for n, _ in items)
        if len(set(nums)) != len(nums):
            raise InputError(f"{d}: array {name!r} has two files for mic {nums[0]}")
        out[name] = [w for _, w in sorted(items)]
    return out


def _init_arrays(d, wavs, model, layout):
    """The [[arrays]] of :func:`init_session` and one comment line each."""
    arrays, notes = [], []
    units = _group_per_mic(d, wavs) if layout == "per-mic" else {w.stem: [w] for w in wavs}
    for name, files in units.items():
        m = model.get(name, "custom") if isinstance(model, dict) else model
        infos = [_audio(f) for f in files]
        if layout == "per-mic":
            bad = [(f, i.channels) for f, i in zip(files, infos) if i.channels != 1]
            if bad:
                raise InputError(f"{bad[0][0]}: {bad[0][1]} channels (--layout per-mic: one mono file per mic)")
            mics, chans = model_layout(m, len(files), f"{d}: array {name!r} ({len(files)} files)")
            if chans is not None:
                raise InputError(f"{d}: array {name!r} has {len(files)} files, but a {m} has {len(mics)} mics")
        else:
            mics, chans = model_layout(m, infos[0].channels, str(files[0]))
        planar = np.ptp(mics[:, 2]) == 0 and m != "custom"
        entry = {"name": name, "mics": mics, "channels": chans, "doa_hemisphere": PLANAR_HEMISPHERE if planar else None}
        entry.update({"files": [f.name for f in files]} if layout == "per-mic" else {"wav": files[0].name})
        arrays.append(entry)
        notes.append(f"# {name}: {m}" + (f" ({BOARDS[m].note}; source: {BOARDS[m].source})" if m in BOARDS else
                                        ": FILL IN the mic positions (m, array frame, one row per channel)"))
    return arrays, notes


def init_session(folder, model, *, reference=None, chirp=None, speed_of_sound=343.0, layout="array"):
    """``session.toml`` text for the WAVs of ``folder``.

    model : a name of :data:`BOARDS` or "custom" (mics left as zeros to fill in), or {array name: model}. A WAV
        in the board's raw layout (more channels than mics) gets the board's channel map.
    layout : "array" (each WAV one array, named after the file) or "per-mic" (one mono WAV per mic, named
        ``<array>-<mic>.wav``, mics in the order of their numbers: the seed paper's ``arr<i>-<m>.wav``).
    chirp : the [chirp] values (default: :func:`chirp_files`'s defaults, with reference = chirp.wav if present).
    Raises InputError when the folder has no WAV or a WAV's channel count does not fit its model.
    """
    d = Path(folder)
    if layout not in LAYOUTS:
        raise InputError(f"--layout must be one of {', '.join(LAYOUTS)}, not {layout!r}")
    wavs = sorted(p for p in d.glob("*.wav") if p.name != "chirp.wav")
    if not wavs:
        raise InputError(f"{d}: no array WAV files (*.wav other than chirp.wav)")
    arrays, notes = _init_arrays(d, wavs, model, layout)
    if chirp is None:
        chirp = {"f0": CHIRP_F0, "f1": CHIRP_F1, "duration": CHIRP_DURATION, "fade": CHIRP_FADE}
        if (d / "chirp.wav").is_file():
            chirp["reference"] = "chirp.wav"
    ref = reference or arrays[0]["name"]
    if ref not in [a["name"] for a in arrays]:
        raise InputError(f"{d}: reference array {ref!r} is not one of {', '.join(a['name'] for a in arrays)}")
    head = "# written by `calib init`; check every value (docs/formats.md)\n" + "\n".join(notes) + "\n"
    return head + session_toml(speed_of_sound, ref, chirp, arrays)


# ----------------------------------------------------------------------------------------------- check
# An array that matched fewer than this fraction of the events probably cannot hear the chirp well enough
MIN_MATCHED_FRACTION = 0.5
# Odometry: a step longer than this between two chirps is implausible for an indoor robot (m)
MAX_STEP_M = 5.0
# Odometry extent (m) below which array positions are poorly determined along that axis
MIN_SPAN_M = 0.5


def _row(what, check, status, detail):
    return {"what": what, "check": check, "status": status, "detail": detail}


def _check_events(session):
    ev = session["events"]
    rows = [_row("events.csv", "events", "ok" if len(ev) >= 3 else "FAIL", f"{len(ev)} events (at least 3 needed)")]
    t = ev["t_emit"].to_numpy(float)
    dur = session["chirp"].get("duration")
    if len(t) > 1 and dur is not None:
        gap = float(np.min(np.diff(t)))
        rows.append(_row("events.csv", "intervals", "ok" if gap > dur else "FAIL",
                         f"shortest interval {gap:.3g} s vs chirp {dur:.3g} s"))
    odo = ev[["odom_x", "odom_y", "odom_z"]].to_numpy(float)
    step = np.linalg.norm(np.diff(odo, axis=0), axis=1) if len(odo) > 1 else np.zeros(1)
    rows.append(_row("events.csv", "odometry steps", "ok" if step.max() <= MAX_STEP_M else "warn",
                     f"largest step {step.max():.2f} m (> {MAX_STEP_M:g} m is implausible)"))
    span = np.ptp(odo, axis=0)
    small = [ax for ax, s in zip("xyz", span) if s < MIN_SPAN_M]
    rows.append(_row("events.csv", "odometry span", "warn" if len(small) > 1 else "ok",
                     "span x {:.2f}, y {:.2f}, z {:.2f} m".format(*span) +
                     (f"; small along {', '.join(small)}: poses weakly determined there" if small else "")))
    return rows


def _check_audio(session):
    from calib.frontend.signals import read_header

    rows, rates = [], {}
    t_end = float(session["events"]["t_emit"].iloc[-1] - session["events"]["t_emit"].iloc[0])
    for a in session["arrays"]:
        try:
            info = read_header(a)
        except InputError as exc:
            rows.append(_row(a["name"], "channels vs mics", "FAIL", str(exc)))
            continue
        rates[a["name"]] = info.samplerate
        rows.append(_row(a["name"], "channels vs mics", "ok", f"{info.channels} channels, {len(a['mics'])} mics"))
        dur = info.frames / info.samplerate
        rows.append(_row(a["name"], "duration", "ok" if dur > t_end else "FAIL",
                         f"{dur:.1f} s recorded, events span {t_end:.1f} s"))
        f1 = max(session["chirp"].get("f0") or 0, session["chirp"].get("f1") or 0)
        rows.append(_row(a["name"], "rate", "ok" if f1 < 0.5 * info.samplerate else "FAIL",
                         f"{info.samplerate} Hz (chirp up to {f1:g} Hz)"))
    if len(set(rates.values())) > 1:
        rows.append(_row("arrays", "rates", "warn", "different sample rates: " +
                         ", ".join(f"{k} {v}" for k, v in rates.items()) + " (allowed; each array on its own)"))
    return rows


def _check_detections(session, options):
    from calib.frontend import extract_features

    try:
        feats, diag = extract_features(session, **options)
    except InputError as exc:
        return [_row("frontend", "chirp audible", "FAIL", str(exc))] + _check_setup(session, None, None, options)
    rows, n = [], len(session["events"])
    for name, a in diag["arrays"].items():
        matched = sum(d["event"] is not None for d in a["detections"])
        ok = matched >= MIN_MATCHED_FRACTION * n
        rows.append(_row(name, "chirp audible", "ok" if ok else "FAIL",
                         f"{matched}/{n} events heard, {len(a['spurious'])} spurious" +
                         (f"; missed {a['missed_events'][:8]}" if a["missed_events"] else "")))
        for w in a["warnings"]:
            rows.append(_row(name, "frontend", "warn", w))
    return rows + _check_setup(session, diag, feats, options)


SETUP_STATUS = {"failed": "FAIL", "suspect": "warn", "note": "ok"}


def _check_setup(session, diag, feats, options):
    """The set-up consistency stage (``calib.pipeline.setupcheck``): one row per finding, or one ok row."""
    from calib.pipeline.setupcheck import setup_findings

    try:
        found = setup_findings(session, diag, feats, options.get("threshold", 8.0))
    except InputError as exc:
        return [_row("set-up", "consistency", "FAIL", str(exc))]
    if not found:
        return [_row("set-up", "consistency", "ok", "channels, mic geometry, clocks, recordings, speed of sound "
                                                      "and trajectory consistent with the data")]
    return [_row(f.what, f.check, SETUP_STATUS[f.status], f.text) for f in found]


def check_session(folder, *, detect=True, **options):
    """Validate a recording session without estimating. Returns a DataFrame (what, check, status, detail) with
    status ok, warn or FAIL. detect: also run the frontend (is the chirp audible in each array?)."""
    from calib.pipeline.formats.session import read_session

    try:
        session = read_session(folder, check_audio=False)  # audio problems: listed below, one row each
    except InputError as exc:
        return pd.DataFrame([_row("session", "session.toml / events.csv", "FAIL", str(exc))])
    rows = _check_events(session) + _check_audio(session)
    if detect and not any(r["status"] == "FAIL" and r["check"] in ("channels vs mics", "rate") for r in rows):
        rows += _check_detections(session, options)
    return pd.DataFrame(rows)
