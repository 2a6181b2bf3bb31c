"""Recording sessions (FORMATS.md section 1): ``session.toml`` + one WAV per array + ``events.csv``.

A session in memory is a plain dict::

    {
      "dir": Path,                      # the session folder
      "speed_of_sound": float,          # m/s
      "reference_array": str,
      "chirp": {"f0": Hz, "f1": Hz, "duration": s, "reference": Path | None},
      "noise": {"sigma_tdoa": s, "sigma_doa_deg": deg, "sigma_odo": m},   # only the keys given
      "arrays": [{"name": str, "wav": Path, "mics": (M, 3) ndarray,
                  "doa_hemisphere": (3,) ndarray | None}, ...],
      "events": DataFrame (event, t_emit, odom_x, odom_y, odom_z),
    }
"""
from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np

from calib.frontend.signals import SWEEP_KINDS

from .io import InputError, atomic_write_text, read_events, SIGMA_KEYS


def read_session(directory):
    """Read and validate a recording session folder. WAV files are checked to exist, not opened."""
    d = Path(directory)
    if not d.is_dir():
        raise InputError(f"{d}: not a directory")
    p = d / "session.toml"
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    try:
        cfg = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: invalid TOML ({exc})") from None

    def num(table, key, where, default=None, positive=True):
        if key not in table:
            if default is None:
                raise InputError(f"{p}: missing '{where}{key}'")
            return default
        v = table[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"{p}: '{where}{key}' is not a finite number")
        if positive and v <= 0:
            raise InputError(f"{p}: '{where}{key}' must be positive")
        return float(v)

    c = num(cfg, "speed_of_sound", "", default=343.0)
    chirp_cfg = cfg.get("chirp")
    if not isinstance(chirp_cfg, dict):
        raise InputError(f"{p}: missing [chirp] table")
    chirp = {"f0": None, "f1": None, "duration": None, "reference": None}
    if "reference" in chirp_cfg:
        ref = d / str(chirp_cfg["reference"])
        if not ref.is_file():
            raise InputError(f"{p}: chirp reference {ref} not found")
        chirp["reference"] = ref
    for key in ("f0", "f1", "duration"):
        if key in chirp_cfg or chirp["reference"] is None:
            chirp[key] = num(chirp_cfg, key, "chirp.")
    if chirp["f0"] is not None and chirp["f1"] is not None and chirp["f0"] == chirp["f1"]:
        raise InputError(f"{p}: chirp.f0 and chirp.f1 must differ")
    kind = chirp_cfg.get("kind", "linear")
    if kind not in SWEEP_KINDS:
        raise InputError(f"{p}: chirp.kind must be one of {', '.join(SWEEP_KINDS)}, not {kind!r}")
    if kind == "exponential" and chirp["f0"] is not None and min(chirp["f0"], chirp["f1"]) <= 0:
        raise InputError(f"{p}: an exponential sweep needs chirp.f0 and chirp.f1 > 0")
    chirp["kind"] = kind
    chirp["fade"] = num(chirp_cfg, "fade", "chirp.", positive=False) if "fade" in chirp_cfg else 0.0
    noise = {k: num(cfg.get("noise", {}), k, "noise.") for k in SIGMA_KEYS if k in cfg.get("noise", {})}

    arrays = []
    if not isinstance(cfg.get("arrays"), list) or not cfg["arrays"]:
        raise InputError(f"{p}: no [[arrays]] given")
    for k, a in enumerate(cfg["arrays"]):
        name = a.get("name")
        if not isinstance(name, str) or not name:
            raise InputError(f"{p}: arrays[{k}] has no name")
        if "wav" not in a:
            raise InputError(f"{p}: array {name!r} has no 'wav'")
        wav = d / str(a["wav"])
        if not wav.is_file():
            raise InputError(f"{wav}: file not found (array {name!r} in {p.name})")
        try:
            mics = np.asarray(a.get("mics"), dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{p}: array {name!r}: 'mics' must be a list of [x, y, z]") from None
        if mics.ndim != 2 or mics.shape[1] != 3 or mics.shape[0] < 1 or not np.all(np.isfinite(mics)):
            raise InputError(f"{p}: array {name!r}: 'mics' must be a non-empty list of [x, y, z]")
        hemi = a.get("doa_hemisphere")
        if hemi is not None:
            hemi = np.asarray(hemi, dtype=float)
            if hemi.shape != (3,) or not np.linalg.norm(hemi) > 0:
                raise InputError(f"{p}: array {name!r}: 'doa_hemisphere' must be a non-zero [x, y, z]")
            hemi = hemi / np.linalg.norm(hemi)
        arrays.append({"name": name, "wav": wav, "mics": mics, "doa_hemisphere": hemi})
    names = [a["name"] for a in arrays]
    if len(set(names)) != len(names):
        raise InputError(f"{p}: duplicate array name")
    ref = cfg.get("reference_array", names[0])
    if ref not in names:
        raise InputError(f"{p}: reference_array {ref!r} is not one of the arrays")
    return {
        "dir": d,
        "speed_of_sound": c,
        "reference_array": ref,
        "chirp": chirp,
        "noise": noise,
        "arrays": arrays,
        "events": read_events(d / "events.csv"),
    }


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


def session_toml(speed_of_sound, reference_array, chirp, arrays, noise=None):
    """Text of a ``session.toml``.

    chirp : dict with f0, f1, duration (and/or reference, a file name relative to the session).
    arrays : list of dicts with name, wav (file name), mics ((M, 3) array-like), optional doa_hemisphere.
    noise : optional dict of sigma_tdoa (s), sigma_doa_deg, sigma_odo (m).
    """
    lines = [f"speed_of_sound = {_toml_value(float(speed_of_sound))}",
             f"reference_array = {_toml_value(reference_array)}", "", "[chirp]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in chirp.items() if v is not None]
    if noise:
        lines += ["", "[noise]"] + [f"{k} = {_toml_value(float(v))}" for k, v in noise.items()]
    for a in arrays:
        lines += ["", "[[arrays]]", f"name = {_toml_value(a['name'])}", f"wav = {_toml_value(str(a['wav']))}"]
        lines.append(f"mics = {_toml_value(np.asarray(a['mics'], float).tolist())}")
        if a.get("doa_hemisphere") is not None:
            lines.append(f"doa_hemisphere = {_toml_value(np.asarray(a['doa_hemisphere'], float).tolist())}")
    return "\n".join(lines) + "\n"


def write_session_toml(path, **kw):
    """Atomically write ``session.toml`` (keyword arguments as :func:`session_toml`)."""
    atomic_write_text(path, session_toml(**kw))
