"""Typed calibration results (dataclasses with DataFrame views) and the helpers a downstream tool needs.

``cal = load_calibration("out/calibration")`` reads ``calibration.json`` (docs/formats.md) into a
:class:`Calibration` (``to_calibration(calibrate(features), features)`` builds one in memory):

- ``cal.mics("reference")`` (all mics, arrays in calibration order, channels in WAV order, (M, 3)),
  ``cal.mics("A2")`` (A2's mics in its own frame), ``cal.mics("reference", array="A2")``,
  ``cal.mics("A3", array="A2")`` (A2's mics in A3's frame);
- ``cal.to_emitter_time("A2", T)`` / ``cal.to_local_time("A2", t)``: an array's local time (WAV sample / fs)
  ↔ the emitter's time (events.csv ``t_emit``); ``cal.to_reference_time("A2", T)``: the reference array's local
  time of the same instant. ``chirp=True`` adds the matched-filter bias β·δ of the calibration chirp;
  ``header=True`` counts local time as WAV sample / the header's rate (an array taken at a measured or declared
  ``sample_rate``: calibration.json ``header_sample_rate``); ``cal.header_clock("A2")``: its total offset and
  drift on that time base;
- ``cal.arrays_frame()``, ``cal.sources_frame()``: DataFrame views (public columns only).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

from calib.clock import header_time_base
from calib.errors import InputError
from calib.jsonutil import dumps_json

from calib.pipeline.formats import validate as V
from calib.pipeline.formats.calibration_json import FORMAT_NAME, FORMAT_VERSION

REFERENCE = "reference"


@dataclass(frozen=True)
class ArrayCalibration:
    """One calibrated array. position (3,) m and quaternion (4,) scalar-first map its frame into the reference
    frame; mics (M, 3) its own frame (None when unknown); offset (s, relative to the reference array) and drift.
    undetermined: the parameters the data left undetermined (e.g. "roll" of a mic pair, "orientation" of a
    single microphone); axis (3,) a linear array's / mic pair's axis in its own frame (None otherwise)."""

    name: str
    position: np.ndarray
    quaternion: np.ndarray
    mics: np.ndarray | None
    offset: float
    drift: float
    std: dict = field(default_factory=dict)
    undetermined: tuple = ()
    axis: np.ndarray | None = None
    # steps and drift terms beyond the linear clock (calib.clock.Clock with offset 0, drift 0, t0 0)
    clock_extra: object = None
    # Hz: the rate its local time counts WAV samples at (local time = sample / sample_rate); None: its header's
    sample_rate: int | None = None
    # Hz: the rate its WAV header states, where sample_rate differs from it (None: unknown, or files before it)
    header_sample_rate: int | None = None

    @property
    def rate_scale(self) -> float:
        """sample_rate / header_sample_rate: its local time on its header's time base (WAV sample / header
        rate) is this × its local time; 1 where either is not known."""
        if self.sample_rate is None or self.header_sample_rate is None:
            return 1.0
        return self.sample_rate / self.header_sample_rate

    @property
    def rotation(self) -> Rotation:
        from scipy.spatial.transform import Rotation  # (~0.1 s to load: only when asked for)

        return Rotation.from_quat(self.quaternion, scalar_first=True)

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous transform array frame → reference frame."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.rotation.as_matrix(), self.position
        return T


@dataclass(frozen=True)
class ClockModel:
    """T_i = (1 + drift_i)(t − t0) + offset_i + reference_offset [+ beta·drift_i] (docs/formats.md)."""

    t0: float
    reference_offset: float | None
    chirp_drift_bias: float
    drift_reference: str | None = None
    # emission times off by a common term (calibration.json clock.emitter): events.csv = true − h_emitter
    emitter: object = None


@dataclass(frozen=True)
class Calibration:
    """A calibration read from calibration.json. ``arrays`` in calibration order."""

    reference_array: str
    speed_of_sound: float
    arrays: tuple
    clock: ClockModel
    covariance: pd.DataFrame | None
    sources: pd.DataFrame | None
    odometry_frame: dict | None
    document: dict

    # ------------------------------------------------------------------ lookup and views
    @property
    def names(self) -> list[str]:
        return [a.name for a in self.arrays]

    def array(self, name: str) -> ArrayCalibration:
        for a in self.arrays:
            if a.name == name:
                return a
        raise KeyError(f"no array {name!r} (arrays: {', '.join(self.names)})")

    def arrays_frame(self) -> pd.DataFrame:
        """arrays.csv's columns (array, x, y, z, qw, qx, qy, qz, offset, drift) + n_mics."""
        return pd.DataFrame([{"array": a.name, **dict(zip("xyz", a.position)),
                              **dict(zip(("qw", "qx", "qy", "qz"), a.quaternion)), "offset": a.offset,
                              "drift": a.drift, "n_mics": 0 if a.mics is None else len(a.mics)} for a in self.arrays])

    def sources_frame(self) -> pd.DataFrame | None:
        return None if self.sources is None else self.sources.copy()

    # ------------------------------------------------------------------ geometry
    def _to_frame(self, points_ref, frame):
        if frame == REFERENCE:
            return points_ref
        a = self.array(frame)
        return a.rotation.inv().apply(points_ref - a.position)

    def mics(self, frame: str = REFERENCE, array: str | None = None) -> np.ndarray:
        """Mic positions (M, 3) m in ``frame`` ("reference" or an array name).

        array : one array's mics (WAV channel order); None = all arrays in calibration order, stacked.
        """
        arrays = self.arrays if array is None else (self.array(array),)
        missing = [a.name for a in arrays if a.mics is None]
        if missing:
            raise InputError(f"no mic geometry for array(s) {', '.join(missing)} (features/meta.json without 'mics')")
        ref = np.vstack([a.rotation.apply(a.mics) + a.position for a in arrays])
        return self._to_frame(ref, frame)

    def transform(self, points: ArrayLike, from_frame: str, to_frame: str = REFERENCE) -> np.ndarray:
        """Points (n, 3) m from one frame ("reference" or an array name) to another."""
        p = np.atleast_2d(np.asarray(points, float))
        if from_frame != REFERENCE:
            a = self.array(from_frame)
            p = a.rotation.apply(p) + a.position
        return self._to_frame(p, to_frame)

    # ------------------------------------------------------------------ clocks
    def _tau(self, name):
        if self.clock.reference_offset is None:
            raise InputError("calibration.json has no clock.reference_offset (features without the reference "
                             "array's detections): the emitter time is not known")
        return self.array(name).offset + self.clock.reference_offset

    def _clock(self, name):
        """The array's :class:`calib.clock.Clock` (local time of true emitter time), steps and terms included."""
        from calib.clock import Clock

        a = self.array(name)
        if not (np.isfinite(a.offset) and np.isfinite(a.drift)):
            raise InputError(f"calibration.json: array {name}'s clock is unknown (the calibration failed: report.json's "
                             "verdict names it)")
        ex = a.clock_extra or Clock()
        return Clock(self._tau(name), a.drift, self.clock.t0, ex.steps, ex.terms)

    def _emitter_extra(self, t):
        e = self.clock.emitter
        return 0.0 if e is None else e.extra(np.asarray(t, float) - self.clock.t0)

    def to_emitter_time(self, name: str, local_time: ArrayLike, chirp: bool = False,
                        header: bool = False) -> np.ndarray:
        """Emitter time (events.csv clock) of the array's local time(s) (s), through its clock model (steps:
        inside an inserted block, the step's time). chirp: the arrival was measured by matched filtering the
        calibration chirp (subtract its bias β·δ). header: the local time is WAV sample / its header's rate
        (``header_sample_rate``), not / its ``sample_rate`` (an array taken at a declared or measured rate)."""
        a = self.array(name)
        bias = self.clock.chirp_drift_bias * a.drift if chirp else 0.0
        local = np.asarray(local_time, float) / (a.rate_scale if header else 1.0)
        t = self._clock(name).emitter(local - bias)
        return t - self._emitter_extra(t)

    def to_local_time(self, name: str, emitter_time: ArrayLike, chirp: bool = False,
                      header: bool = False) -> np.ndarray:
        """The array's local time(s) of emitter time(s): the inverse of :meth:`to_emitter_time`."""
        a = self.array(name)
        bias = self.clock.chirp_drift_bias * a.drift if chirp else 0.0
        t = np.asarray(emitter_time, float)
        return (self._clock(name).local(t + self._emitter_extra(t)) + bias) * (a.rate_scale if header else 1.0)

    def to_reference_time(self, name: str, local_time: ArrayLike, chirp: bool = False,
                          header: bool = False) -> np.ndarray:
        """The reference array's local time of the instant the array ``name`` reads as ``local_time``."""
        t = self.to_emitter_time(name, local_time, chirp, header)
        return self.to_local_time(self.reference_array, t, chirp, header)

    def header_clock(self, name: str) -> tuple[float, float]:
        """(offset, drift) of the array's linear clock on its header's time base (WAV sample / header rate):
        for an array taken at a declared or measured rate, its total drift and offset against the emitter
        (``calib.clock.header_time_base``; the offset relative to the reference array's header time base)."""
        a, ref = self.array(name), self.array(self.reference_array)
        tau = self.clock.reference_offset   # (needed only where the two time bases differ: NaN when unknown)
        tau = 0.0 if a.rate_scale == ref.rate_scale else np.nan if tau is None else tau
        offset, drift = header_time_base(a.offset, a.drift, a.rate_scale, ref.rate_scale, tau)
        return float(offset), float(drift)


# ------------------------------------------------------------------ reading calibration.json (validated)
QUATERNION_NORM_TOL = 1e-3  # a stored unit quaternion is renormalised within this; beyond, it is not a rotation
MAX_ABS_CAL_DRIFT = 0.5     # |drift| of a stored calibration: 1 + drift must stay a positive clock rate
MAX_ABS_MIC = 10.0          # m: mic coordinates in the array's frame (as session.toml)


def _obj(value, where, *, optional=False):
    """A JSON object (dict), or None when ``optional``."""
    if value is None and optional:
        return None
    if not isinstance(value, dict):
        raise InputError(f"{where} must be an object, not {V.show(value)}")
    return value


def _list(value, where, *, optional=False, max_len=None):
    if value is None and optional:
        return None
    if not isinstance(value, list):
        raise InputError(f"{where} must be a list, not {V.show(value)}")
    if max_len is not None and len(value) > max_len:
        raise InputError(f"{where}: {len(value)} entries, more than {max_len}")
    return value


def _quaternion(value, where):
    """A unit quaternion [w, x, y, z] (renormalised within QUATERNION_NORM_TOL)."""
    if not isinstance(value, list) or len(value) != 4:
        raise InputError(f"{where} must be [w, x, y, z], not {V.show(value)}")
    q = np.array([V.number(v, where, lo=-2.0, hi=2.0) for v in value])
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise InputError(f"{where}: {V.show(value)} is not a unit quaternion (norm {norm:.4g}): not a rotation")
    return q / norm


def _points(value, where, bound):
    rows = _list(value, where, max_len=V.MAX_MICS)
    return np.array([V.vector3(r, f"{where}[{k}]", bound=bound) for k, r in enumerate(rows)], float).reshape(-1, 3)


def _std_entry(value, where):
    std = _obj(value, where, optional=True) or {}
    for k, v in std.items():
        if isinstance(v, list):
            for x in v:
                V.number(x, f"{where}.{k}", lo=0.0, allow_none=True)
        else:
            V.number(v, f"{where}.{k}", lo=0.0, allow_none=True)
    return dict(std)


def _position(value, where):
    """[x, y, z] m, or NaN (3,) for null: a position the calibration could not give (a diverged solve's)."""
    return np.full(3, np.nan) if value is None else np.array(V.vector3(value, where))


def _or_nan(v):
    return float("nan") if v is None else v


def _array(entry, where):
    entry = _obj(entry, where)
    name = V.string(entry.get("name"), f"{where}.name")
    where = f"{where} ({name})"
    clock = _obj(entry.get("clock"), f"{where}.clock")
    mics = entry.get("mics")
    und = _list(entry.get("undetermined"), f"{where}.undetermined", optional=True) or []
    axis = entry.get("axis")
    return ArrayCalibration(
        name=name, position=_position(entry.get("position"), f"{where}.position"),
        quaternion=_quaternion(entry.get("quaternion"), f"{where}.quaternion"),
        mics=None if mics is None else _points(mics, f"{where}.mics", MAX_ABS_MIC),
        # null: a clock that ran off (estimator.outputs.blank_diverged), unknown as a null position
        offset=_or_nan(V.number(clock.get("offset"), f"{where}.clock.offset", lo=-V.MAX_ABS_TIME, hi=V.MAX_ABS_TIME,
                                allow_none=True)),
        drift=_or_nan(V.number(clock.get("drift"), f"{where}.clock.drift", lo=-MAX_ABS_CAL_DRIFT, hi=MAX_ABS_CAL_DRIFT,
                               allow_none=True)),
        std=_std_entry(entry.get("std"), f"{where}.std"),
        undetermined=tuple(V.string(u, f"{where}.undetermined") for u in und),
        axis=None if axis is None else np.array(V.vector3(axis, f"{where}.axis", nonzero=True)),
        clock_extra=_clock_extra(clock, f"{where}.clock"),
        sample_rate=V.number(clock.get("sample_rate"), f"{where}.clock.sample_rate", lo=V.SAMPLE_RATE[0],
                             hi=V.SAMPLE_RATE[1], integer=True, allow_none=True),
        header_sample_rate=V.number(clock.get("header_sample_rate"), f"{where}.clock.header_sample_rate",
                                    lo=V.SAMPLE_RATE[0], hi=V.SAMPLE_RATE[1], integer=True, allow_none=True))


def _clock_extra(ck, where):
    """The steps and drift terms of a calibration.json clock entry as a :class:`calib.clock.Clock` (offset 0,
    drift 0, t0 0), or None when it has none (the linear clock; files before these keys)."""
    from calib.clock import Clock

    if not ck or not (ck.get("steps") or ck.get("drift_terms")):
        return None
    try:
        return Clock.from_dict({"steps": _list(ck.get("steps"), f"{where}.steps", optional=True) or (),
                                "terms": [{"kind": d["kind"], **{k: v for k, v in d.items() if k not in ("kind", "std")}}
                                          for d in _list(ck.get("drift_terms"), f"{where}.drift_terms",
                                                         optional=True) or ()]})
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"{where}: malformed clock model ({type(exc).__name__}: {exc})") from None


def _clock(value, where):
    ck = _obj(value, where)
    t = (-V.MAX_ABS_TIME, V.MAX_ABS_TIME)
    drift_ref = ck.get("drift_reference")
    return ClockModel(t0=V.number(ck.get("t0"), f"{where}.t0", lo=t[0], hi=t[1]),
                      reference_offset=V.number(ck.get("reference_offset"), f"{where}.reference_offset", lo=t[0],
                                                hi=t[1], allow_none=True),
                      chirp_drift_bias=V.number(ck.get("chirp_drift_bias") or 0.0, f"{where}.chirp_drift_bias",
                                                lo=t[0], hi=t[1]),
                      drift_reference=None if drift_ref is None else V.string(drift_ref, f"{where}.drift_reference"),
                      emitter=_clock_extra(_obj(ck.get("emitter"), f"{where}.emitter", optional=True),
                                           f"{where}.emitter"))


def _covariance(value, where):
    cov = _obj(value, where, optional=True)
    if cov is None:
        return None
    labels = [V.string(x, f"{where}.parameters") for x in _list(cov.get("parameters"), f"{where}.parameters")]
    if len(set(labels)) != len(labels):
        raise InputError(f"{where}.parameters: a parameter is listed twice")
    rows = _list(cov.get("matrix"), f"{where}.matrix")
    if len(rows) != len(labels) or not all(isinstance(r, list) and len(r) == len(labels) for r in rows):
        raise InputError(f"{where}.matrix must be {len(labels)} × {len(labels)} (one row and column per parameter)")
    m = np.array([[V.number(x, f"{where}.matrix") for x in r] for r in rows], float).reshape(len(labels), -1)
    return pd.DataFrame(m, index=labels, columns=labels)


def _sources(value, where):
    src = _list(value, where, optional=True, max_len=V.MAX_EVENTS)
    if src is None:
        return None
    rows = []
    for k, s in enumerate(src):
        s = _obj(s, f"{where}[{k}]")
        ev = V.number(s.get("event"), f"{where}[{k}].event", lo=0, hi=V.MAX_EVENT_ID, integer=True)
        rows.append({"event": ev, **dict(zip("xyz", _position(s.get("position"), f"{where}[{k}].position")))})
    return pd.DataFrame(rows, columns=["event", "x", "y", "z"])


def _format_version(doc, path):
    v = doc.get("format_version")
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise InputError(f"{path}: 'format_version' must be an integer ≥ 1, not {V.show(v)}")
    if v > FORMAT_VERSION:
        raise InputError(f"{path}: format_version {v} is newer than this calib reads ({FORMAT_VERSION}): upgrade calib")


def from_document(doc, path="calibration.json"):
    """A :class:`Calibration` from a calibration.json dict; every field it uses is validated (InputError naming
    the file and the field)."""
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise InputError(f"{path}: not a calib calibration.json (format {FORMAT_NAME!r})")
    doc = json.loads(dumps_json(doc))  # an in-memory document as the file holds it (lists, not arrays)
    _format_version(doc, path)
    items = _list(doc.get("arrays"), f"{path}: 'arrays'", max_len=V.MAX_ARRAYS)
    if not items:
        raise InputError(f"{path}: 'arrays' is empty")
    arrays = tuple(_array(e, f"{path}: arrays[{k}]") for k, e in enumerate(items))
    names = [a.name for a in arrays]
    if len(set(names)) != len(names):
        raise InputError(f"{path}: 'arrays': two arrays are named {next(n for n in names if names.count(n) > 1)!r}")
    ref = V.string(doc.get("reference_array"), f"{path}: 'reference_array'")
    if ref not in names:
        raise InputError(f"{path}: 'reference_array' {ref!r} is not one of the arrays ({', '.join(names)})")
    odo = _obj(doc.get("odometry_frame"), f"{path}: 'odometry_frame'", optional=True)
    return Calibration(reference_array=ref, speed_of_sound=V.speed_of_sound(doc.get("speed_of_sound"),
                                                                             f"{path}: 'speed_of_sound'"),
                       arrays=arrays, clock=_clock(doc.get("clock"), f"{path}: 'clock'"),
                       covariance=_covariance(doc.get("covariance"), f"{path}: 'covariance'"),
                       sources=_sources(doc.get("sources"), f"{path}: 'sources'"), odometry_frame=odo, document=doc)


def to_calibration(calib, features) -> Calibration:
    """A :class:`Calibration` from an in-memory result of ``estimator.calibrate(features)`` (no files)."""
    from calib.pipeline.formats.calibration_json import calibration_document

    return from_document(calibration_document(calib, features), "calibration")


def load_calibration(path) -> Calibration:
    """Read ``calibration.json`` (a file, or a calibration/ folder holding one) into a :class:`Calibration`."""
    p = Path(path)
    if p.is_dir():
        p = p / "calibration.json"
    if not p.is_file():
        raise InputError(f"{p}: file not found (written by `calib estimate` / `calib run` since calib 0.2)")
    try:
        doc = json.loads(V.read_text(p))  # (UTF-8; a byte-order mark is ignored, as in every reader)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{p}: invalid JSON ({str(exc).splitlines()[0][:120]})") from None
    return from_document(doc, p)
