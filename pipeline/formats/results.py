"""Typed calibration results (dataclasses with DataFrame views) and the helpers a downstream tool needs.

``cal = load_calibration("out/calibration")`` reads ``calibration.json`` (docs/formats.md) into a
:class:`Calibration` (``to_calibration(calibrate(features), features)`` builds one in memory):

- ``cal.mics("reference")`` (all mics, arrays in calibration order, channels in WAV order, (M, 3)),
  ``cal.mics("A2")`` (A2's mics in its own frame), ``cal.mics("reference", array="A2")``,
  ``cal.mics("A3", array="A2")`` (A2's mics in A3's frame);
- ``cal.to_emitter_time("A2", T)`` / ``cal.to_local_time("A2", t)``: an array's local time (WAV sample / fs)
  ↔ the emitter's time (events.csv ``t_emit``); ``cal.to_reference_time("A2", T)``: the reference array's local
  time of the same instant. ``chirp=True`` adds the matched-filter bias β·δ of the calibration chirp;
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

from calib.errors import InputError

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
        ex = a.clock_extra or Clock()
        return Clock(self._tau(name), a.drift, self.clock.t0, ex.steps, ex.terms)

    def _emitter_extra(self, t):
        e = self.clock.emitter
        return 0.0 if e is None else e.extra(np.asarray(t, float) - self.clock.t0)

    def to_emitter_time(self, name: str, local_time: ArrayLike, chirp: bool = False) -> np.ndarray:
        """Emitter time (events.csv clock) of the array's local time(s) (s), through its clock model (steps:
        inside an inserted block, the step's time). chirp: the arrival was measured by matched filtering the
        calibration chirp (subtract its bias β·δ)."""
        a = self.array(name)
        bias = self.clock.chirp_drift_bias * a.drift if chirp else 0.0
        t = self._clock(name).emitter(np.asarray(local_time, float) - bias)
        return t - self._emitter_extra(t)

    def to_local_time(self, name: str, emitter_time: ArrayLike, chirp: bool = False) -> np.ndarray:
        """The array's local time(s) of emitter time(s): the inverse of :meth:`to_emitter_time`."""
        a = self.array(name)
        bias = self.clock.chirp_drift_bias * a.drift if chirp else 0.0
        t = np.asarray(emitter_time, float)
        return self._clock(name).local(t + self._emitter_extra(t)) + bias

    def to_reference_time(self, name: str, local_time: ArrayLike, chirp: bool = False) -> np.ndarray:
        """The reference array's local time of the instant the array ``name`` reads as ``local_time``."""
        t = self.to_emitter_time(name, local_time, chirp)
        return self.to_local_time(self.reference_array, t, chirp)


def _array(entry):
    mics = entry.get("mics")
    return ArrayCalibration(name=str(entry["name"]), position=np.asarray(entry["position"], float),
                            quaternion=np.asarray(entry["quaternion"], float),
                            mics=None if mics is None else np.asarray(mics, float).reshape(-1, 3),
                            offset=float(entry["clock"]["offset"]), drift=float(entry["clock"]["drift"]),
                            std=dict(entry.get("std") or {}),
                            undetermined=tuple(str(u) for u in entry.get("undetermined") or ()),
                            axis=None if entry.get("axis") is None else np.asarray(entry["axis"], float),
                            clock_extra=_clock_extra(entry["clock"]))


def _clock_extra(ck):
    """The steps and drift terms of a calibration.json clock entry as a :class:`calib.clock.Clock` (offset 0,
    drift 0, t0 0), or None when it has none (the linear clock; files before these keys)."""
    from calib.clock import Clock

    if not ck or not (ck.get("steps") or ck.get("drift_terms")):
        return None
    return Clock.from_dict({"steps": ck.get("steps") or (),
                            "terms": [{"kind": d["kind"], **{k: v for k, v in d.items() if k not in ("kind", "std")}}
                                      for d in ck.get("drift_terms") or ()]})


def from_document(doc, path="calibration.json"):
    """A :class:`Calibration` from a calibration.json dict. Raises InputError on a wrong format or version."""
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise InputError(f"{path}: not a calib calibration.json (format {FORMAT_NAME!r})")
    if int(doc.get("format_version", 0)) > FORMAT_VERSION:
        raise InputError(f"{path}: format_version {doc.get('format_version')} is newer than this calib reads "
                         f"({FORMAT_VERSION}): upgrade calib")
    try:
        arrays = tuple(_array(e) for e in doc["arrays"])
        ck = doc["clock"]
        clock = ClockModel(t0=float(ck["t0"]), reference_offset=ck.get("reference_offset"),
                           chirp_drift_bias=float(ck.get("chirp_drift_bias") or 0.0),
                           drift_reference=ck.get("drift_reference"), emitter=_clock_extra(ck.get("emitter")))
        cov = doc.get("covariance")
        cov = None if cov is None else pd.DataFrame(np.asarray(cov["matrix"], float), index=cov["parameters"],
                                                    columns=cov["parameters"])
        src = doc.get("sources")
        src = None if src is None else pd.DataFrame(
            [{"event": s["event"], **dict(zip("xyz", s["position"]))} for s in src])
        return Calibration(reference_array=str(doc["reference_array"]), speed_of_sound=float(doc["speed_of_sound"]),
                           arrays=arrays, clock=clock, covariance=cov, sources=src,
                           odometry_frame=doc.get("odometry_frame"), document=doc)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: malformed calibration.json ({type(exc).__name__}: {exc})") from None


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
        doc = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: invalid JSON ({exc})") from None
    return from_document(doc, p)
