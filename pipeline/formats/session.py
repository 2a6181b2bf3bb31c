"""Recording sessions (docs/formats.md section 1): ``session.toml`` + one WAV per array + ``events.csv``.

A session in memory is a :class:`calib.records.Session`, which reads like this dict (the frontend also
takes the dict form)::

    {
      "dir": Path,                      # the session folder
      "speed_of_sound": float,          # m/s
      "reference_array": str,
      "chirp": {"f0": Hz, "f1": Hz, "duration": s, "reference": Path | None},
      "noise": {"sigma_tdoa": s, "sigma_doa_deg": deg, "sigma_odo": m},   # only the keys given
      "arrays": [{"name": str, "wav": Path, "files": (Path, ...), "channels": (int, ...) | None,
                  "mics": (M, 3) ndarray, "doa_hemisphere": (3,) ndarray | None}, ...],
      "robot": {"speaker_offset": (3,) ndarray},   # only the keys given
      "events": DataFrame (event, t_emit, odom_x, odom_y, odom_z): the speaker's positions (speaker_positions),
    }

An array's audio is one multichannel WAV (``wav``; ``files == (wav,)``), optionally with a channel map
(``channels``: the WAV channel of each mic, counted from 0, in the order of ``mics``: a raw board recording with
playback or processed channels too), or one mono file per mic (``files``, in the order of ``mics``; ``wav`` is
the first of them).
"""
from __future__ import annotations

from calib.tomlcompat import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from calib.frontend.signals import SWEEP_KINDS

from calib.errors import InputWarning

from calib.pipeline.formats import validate as V
from calib.kinds import noise_keys
from calib.records import Session
from calib.pipeline.formats.io import InputError, atomic_write_text, read_events

DEFAULT_SPEED_OF_SOUND = 343.0  # m/s, air at 20 °C
MAX_MIC_RADIUS = 10.0           # m: mic coordinates are relative to their array's centre
SPAN_WAVELENGTHS = 50.0         # an array wider than this many wavelengths is a unit mistake (mm for m)


TOP_KEYS = ("speed_of_sound", "reference_array", "chirp", "noise", "arrays", "robot", "temperature")
ROBOT_KEYS = ("speaker_offset",)
MAX_LEVER_ARM = 5.0             # m: the speaker sits on the robot
TEMPERATURE_C = (-50.0, 60.0)   # °C: the air of a room (optional key, checked against speed_of_sound)
CHIRP_KEYS = ("f0", "f1", "duration", "reference", "kind", "fade")
ARRAY_KEYS = ("name", "wav", "files", "channels", "mics", "doa_hemisphere", "sample_rate")


def read_session(directory, check_audio=True):
    """Read and validate a recording session folder → :class:`calib.records.Session`. WAV headers are checked (channels, sample rate vs
    the chirp band), the samples are not read; ``check_audio=False`` skips that (``calib check`` lists
    every audio problem itself instead of stopping at the first).

    Every value is typed (numbers are TOML numbers, not strings or booleans) and within the ranges of
    ``pipeline/formats/validate.py``; unknown keys warn with a did-you-mean (:class:`calib.errors.InputWarning`).
    """
    d = Path(directory)
    if not d.is_dir():
        raise InputError(f"{d}: not a directory")
    p = d / "session.toml"
    try:
        cfg = tomllib.loads(V.read_text(p))
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise InputError(f"{p}: invalid TOML ({' '.join(str(exc).split())})") from None
    V.check_keys(cfg, TOP_KEYS, str(p))
    c = V.speed_of_sound(cfg.get("speed_of_sound", DEFAULT_SPEED_OF_SOUND), f"{p}: 'speed_of_sound'")
    chirp = _read_chirp(cfg.get("chirp"), d, p)
    noise_cfg = cfg.get("noise", {})
    if not isinstance(noise_cfg, dict):
        raise InputError(f"{p}: [noise] must be a table of {', '.join(noise_keys())}")
    V.check_keys(noise_cfg, noise_keys(), f"{p}: [noise]")
    noise = {k: V.sigma(k, noise_cfg[k], f"{p}: 'noise.{k}'") for k in noise_keys() if k in noise_cfg}
    arrays = _read_arrays(cfg.get("arrays"), d, p)
    names = [a["name"] for a in arrays]
    ref = cfg.get("reference_array", names[0])
    if not isinstance(ref, str) or ref not in names:
        raise InputError(f"{p}: reference_array {ref!r} is not one of the arrays")
    robot = _read_robot(cfg.get("robot", {}), p)
    session = {
        "dir": d,
        "speed_of_sound": c,
        "reference_array": ref,
        "chirp": chirp,
        "noise": noise,
        "arrays": arrays,
        "robot": robot,
        "events": speaker_positions(read_events(d / "events.csv"), robot.get("speaker_offset"), p),
    }
    _check_event_spacing(session["events"], chirp["duration"] or V.CHIRP_DURATION[0])
    if "temperature" in cfg:
        session["temperature"] = V.number(cfg["temperature"], f"{p}: 'temperature'", lo=TEMPERATURE_C[0],
                                          hi=TEMPERATURE_C[1])
    if check_audio:
        _check_audio(session, p)
    return Session.from_dict(session)


def _check_event_spacing(events, duration):
    """One speaker plays one chirp at a time. Emissions closer than the shortest chirp calib accepts (1 ms) are a
    logging mistake (one chirp logged twice, or t_emit in the wrong unit): an error (the association's
    tolerance, a quarter of the smallest spacing, would vanish). Closer than this session's chirp: a warning
    (their chirps overlap)."""
    gaps = np.diff(events["t_emit"].to_numpy())
    if not len(gaps) or gaps.min() >= duration:
        return
    k = int(np.argmin(gaps))
    text = (f"{events.attrs.get('path', 'events.csv')}: event {events['event'].iloc[k + 1]} is logged {gaps[k]:.3g} s "
            f"after event {events['event'].iloc[k]}")
    if gaps[k] < V.CHIRP_DURATION[0]:
        raise InputError(f"{text}, less than any chirp lasts ({V.CHIRP_DURATION[0]:g} s): one chirp logged twice, or "
                         "t_emit in the wrong unit?")
    warnings.warn(f"{text}, less than the chirp's {duration:g} s: their chirps overlap", InputWarning, stacklevel=3)


def _read_robot(cfg, p):
    """The [robot] table → {"speaker_offset": (3,) ndarray} (only the keys given)."""
    if not isinstance(cfg, dict):
        raise InputError(f"{p}: [robot] must be a table (speaker_offset = [x, y, z])")
    V.check_keys(cfg, ROBOT_KEYS, f"{p}: [robot]")
    out = {}
    if "speaker_offset" in cfg:
        out["speaker_offset"] = np.asarray(V.vector3(cfg["speaker_offset"], f"{p}: 'robot.speaker_offset'",
                                                     bound=MAX_LEVER_ARM))
    return out


def speaker_positions(events, speaker_offset, where):
    """events.csv's odometry as the speaker's positions.

    With an ``odom_yaw`` column (the robot's heading, rad; ``calib import-bag`` writes it) the odometry is the
    robot base's pose, and the speaker is at ``odom + Rz(yaw) · speaker_offset`` (``[robot] speaker_offset``, m,
    robot frame: x forward, z up; default 0); the column is consumed. Without it the odometry is the
    speaker's position already, and a speaker_offset is an error (it cannot be rotated)."""
    if "odom_yaw" not in events.columns:
        if speaker_offset is not None:
            raise InputError(f"{where}: [robot] speaker_offset needs the robot's heading: an odom_yaw column (rad) "
                             "in events.csv (calib import-bag writes it)")
        return events
    yaw = pd.to_numeric(events["odom_yaw"], errors="coerce").to_numpy(float)
    if not np.all(np.isfinite(yaw)):
        k = int(np.flatnonzero(~np.isfinite(yaw))[0])
        raise InputError(f"{events.attrs.get('path', 'events.csv')}: event {events['event'].iloc[k]}: odom_yaw must "
                         "be a finite number (rad)")
    off = np.zeros(3) if speaker_offset is None else np.asarray(speaker_offset, float)
    c, s = np.cos(yaw), np.sin(yaw)
    out = events.drop(columns="odom_yaw")
    out["odom_x"] = events["odom_x"] + c * off[0] - s * off[1]
    out["odom_y"] = events["odom_y"] + s * off[0] + c * off[1]
    out["odom_z"] = events["odom_z"] + off[2]
    out.attrs = dict(events.attrs)
    return out


def _read_chirp(chirp_cfg, d, p):
    """The [chirp] table → dict f0, f1, duration, reference, kind, fade (validated)."""
    if not isinstance(chirp_cfg, dict):
        raise InputError(f"{p}: missing [chirp] table")
    V.check_keys(chirp_cfg, CHIRP_KEYS, f"{p}: [chirp]")
    chirp = {"f0": None, "f1": None, "duration": None, "reference": None}
    if "reference" in chirp_cfg:
        ref = d / V.string(chirp_cfg["reference"], f"{p}: 'chirp.reference'")
        if not ref.is_file():
            raise InputError(f"{p}: chirp reference {ref} not found")
        chirp["reference"] = ref
    for key in ("f0", "f1", "duration"):
        if key in chirp_cfg or chirp["reference"] is None:
            if key not in chirp_cfg:
                raise InputError(f"{p}: missing 'chirp.{key}'")
            lo, hi = V.CHIRP_DURATION if key == "duration" else (0.0, V.SAMPLE_RATE[1] / 2)
            chirp[key] = V.number(chirp_cfg[key], f"{p}: 'chirp.{key}'", lo=lo, hi=hi)
    if chirp["f0"] is not None and chirp["f1"] is not None and chirp["f0"] == chirp["f1"]:
        raise InputError(f"{p}: chirp.f0 and chirp.f1 must differ")
    kind = chirp_cfg.get("kind", "linear")
    if kind not in SWEEP_KINDS:
        raise InputError(f"{p}: chirp.kind must be one of {', '.join(SWEEP_KINDS)}, not {kind!r}")
    if kind == "exponential" and chirp["f0"] is not None and min(chirp["f0"], chirp["f1"]) <= 0:
        raise InputError(f"{p}: an exponential sweep needs chirp.f0 and chirp.f1 > 0")
    chirp["kind"] = kind
    chirp["fade"] = 0.0
    if "fade" in chirp_cfg:
        chirp["fade"] = V.number(chirp_cfg["fade"], f"{p}: 'chirp.fade'", lo=0.0,
                                 hi=chirp["duration"] / 2 if chirp["duration"] else None)
    return chirp


def _read_arrays(items, d, p):
    """The [[arrays]] tables → list of dicts name, wav, mics (M, 3), doa_hemisphere (validated)."""
    if not isinstance(items, list) or not items or not all(isinstance(a, dict) for a in items):
        raise InputError(f"{p}: no [[arrays]] given")
    if len(items) > V.MAX_ARRAYS:
        raise InputError(f"{p}: {len(items)} arrays, more than {V.MAX_ARRAYS}")
    arrays, wavs = [], {}
    for k, a in enumerate(items):
        name = a.get("name")
        if not isinstance(name, str) or not name:
            raise InputError(f"{p}: arrays[{k}] needs a 'name' (a non-empty string), not {name!r}")
        V.check_keys(a, ARRAY_KEYS, f"{p}: array {name!r}")
        mics = _read_mics(a.get("mics"), f"{p}: array {name!r}: 'mics'")
        files = _read_files(a, name, len(mics), d, p)
        for f in files:
            real = f.resolve()
            if real in wavs:
                raise InputError(f"{p}: arrays {wavs[real]!r} and {name!r} share one recording {f.name!r}")
            wavs[real] = name
        channels = _read_channels(a.get("channels"), len(mics), f"{p}: array {name!r}: 'channels'")
        if channels is not None and len(files) > 1:
            raise InputError(f"{p}: array {name!r}: 'channels' selects channels of one 'wav'; with one file per mic "
                             "('files') leave it out")
        hemi = a.get("doa_hemisphere")
        if hemi is not None:
            hemi = np.asarray(V.vector3(hemi, f"{p}: array {name!r}: 'doa_hemisphere'", nonzero=True))
            hemi = hemi / np.linalg.norm(hemi)
        # the board's true nominal rate where its WAV header states a wrong one (docs/formats.md)
        rate = V.number(a.get("sample_rate"), f"{p}: array {name!r}: 'sample_rate'", lo=V.SAMPLE_RATE[0],
                        hi=V.SAMPLE_RATE[1], integer=True, allow_none=True)
        arrays.append({"name": name, "wav": files[0], "files": files, "channels": channels, "mics": mics,
                       "doa_hemisphere": hemi, "sample_rate": rate})
    names = [a["name"] for a in arrays]
    if len(set(names)) != len(names):
        raise InputError(f"{p}: duplicate array name")
    return arrays


def _read_files(a, name, n_mics, d, p):
    """The array's audio files: ``(wav,)``, or its ``files`` (one per mic, in the order of ``mics``); each exists."""
    if ("wav" in a) == ("files" in a):
        raise InputError(f"{p}: array {name!r} needs either 'wav' (one multichannel file) or 'files' (one file "
                         "per mic)" + (", not both" if "wav" in a else ""))
    if "wav" in a:
        names = [V.string(a["wav"], f"{p}: array {name!r}: 'wav'")]
    else:
        where = f"{p}: array {name!r}: 'files'"
        if not isinstance(a["files"], list) or not a["files"]:
            raise InputError(f"{where} must be a non-empty list of file names (one per mic)")
        names = [V.string(f, where) for f in a["files"]]
        if len(names) != n_mics:
            raise InputError(f"{where}: {len(names)} files for {n_mics} mics (one file per mic, in the order of 'mics')")
    files = tuple(d / f for f in names)
    for f in files:
        if not f.is_file():
            raise InputError(f"{f}: file not found (array {name!r} in {p.name})")
    return files


def _read_channels(value, n_mics, where):
    """A channel map: one distinct WAV channel (an integer ≥ 0) per mic → tuple, or None when not given."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != n_mics:
        raise InputError(f"{where} must list one WAV channel per mic ({n_mics}, counted from 0), not {value!r}")
    chans = tuple(V.number(c, where, lo=0, hi=V.MAX_CHANNELS - 1, integer=True) for c in value)
    if len(set(chans)) != len(chans):
        raise InputError(f"{where}: channel {max(chans, key=chans.count)} is given for two mics")
    return chans


def _read_mics(value, where):
    """A non-empty list of [x, y, z] (m, within an array's reach), no two mics at one place → (M, 3)."""
    if not isinstance(value, list) or not value:
        raise InputError(f"{where} must be a non-empty list of [x, y, z]")
    if len(value) > V.MAX_MICS:
        raise InputError(f"{where}: {len(value)} mics, more than {V.MAX_MICS}")
    mics = np.array([V.vector3(m, where, bound=MAX_MIC_RADIUS) for m in value])
    dist = np.linalg.norm(mics[:, None] - mics[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    if dist.min() < V.MIN_MIC_SPACING:
        i, j = np.unravel_index(np.argmin(dist), dist.shape)
        raise InputError(f"{where}: mics {i + 1} and {j + 1} are at the same place ({dist[i, j] * 1e3:.2g} mm apart)")
    return mics


def _check_audio(session, p):
    """Each WAV header: channels = mics, sample rate in range, chirp band below Nyquist; warn on spatial aliasing."""
    from calib.frontend.signals import read_header

    chirp, c = session["chirp"], session["speed_of_sound"]
    f_hi = max(chirp["f0"], chirp["f1"]) if chirp["f0"] is not None else None
    for a in session["arrays"]:
        info = read_header(a)
        fs = info.samplerate
        if not V.SAMPLE_RATE[0] <= fs <= V.SAMPLE_RATE[1]:
            raise InputError(f"{a['wav']}: sample rate {fs} Hz is outside [{V.SAMPLE_RATE[0]}, {V.SAMPLE_RATE[1]}] Hz")
        if f_hi is not None and f_hi >= fs / 2:
            raise InputError(f"{p}: the chirp reaches {f_hi:g} Hz, at or above the Nyquist frequency {fs / 2:g} Hz "
                             f"of {a['wav'].name} (array {a['name']!r})")
        if f_hi is not None and len(a["mics"]) > 1:
            span = float(np.max(np.linalg.norm(a["mics"][:, None] - a["mics"][None], axis=2)))
            if span > SPAN_WAVELENGTHS * c / max(f_hi, 1.0):
                warnings.warn(f"{p}: array {a['name']!r} spans {span:.3g} m, more than {SPAN_WAVELENGTHS:g} "
                              f"wavelengths at {f_hi:g} Hz: check the mic coordinates are in metres", InputWarning,
                              stacklevel=3)


def _toml_value(v):
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v)} to TOML")


def session_toml(speed_of_sound, reference_array, chirp, arrays, noise=None, robot=None):
    """Text of a ``session.toml``.

    chirp : dict with f0, f1, duration (and/or reference, a file name relative to the session).
    arrays : list of dicts with name, wav (file name) or files (file names, one per mic), optional channels (the
        WAV channel of each mic, from 0), mics ((M, 3) array-like), optional doa_hemisphere.
    noise : optional dict of sigma_tdoa (s), sigma_doa_deg, sigma_odo (m).
    robot : optional dict of speaker_offset ((3,) m, robot frame).
    """
    lines = [f"speed_of_sound = {_toml_value(float(speed_of_sound))}",
             f"reference_array = {_toml_value(reference_array)}", "", "[chirp]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in chirp.items() if v is not None]
    if noise:
        lines += ["", "[noise]"] + [f"{k} = {_toml_value(float(v))}" for k, v in noise.items()]
    if robot:
        lines += ["", "[robot]"] + [f"{k} = {_toml_value(np.asarray(v, float).tolist())}" for k, v in robot.items()]
    for a in arrays:
        lines += ["", "[[arrays]]", f"name = {_toml_value(a['name'])}"]
        if a.get("files") is not None and len(a["files"]) > 1:
            lines.append(f"files = {_toml_value([str(f) for f in a['files']])}")
        else:
            lines.append(f"wav = {_toml_value(str(a['wav']))}")
        if a.get("channels") is not None:
            lines.append(f"channels = {_toml_value([int(c) for c in a['channels']])}")
        lines.append(f"mics = {_toml_value(np.asarray(a['mics'], float).tolist())}")
        if a.get("doa_hemisphere") is not None:
            lines.append(f"doa_hemisphere = {_toml_value(np.asarray(a['doa_hemisphere'], float).tolist())}")
        if a.get("sample_rate") is not None:
            lines.append(f"sample_rate = {int(a['sample_rate'])}")
    return "\n".join(lines) + "\n"


def write_session_toml(path, **kw):
    """Atomically write ``session.toml`` (keyword arguments as :func:`session_toml`)."""
    atomic_write_text(path, session_toml(**kw))
