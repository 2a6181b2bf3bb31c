"""Typed records that cross stages (frontend or simulator → files → estimator).

:class:`Session` is a recording session as read from its folder (what the frontend takes); :class:`Features`
is the measurements of one session, docs/formats.md section 2. It is frozen (its fields
cannot be re-bound; a changed copy is :meth:`Features.replace`) and reads like the dict earlier versions
passed around (``features["doa"]``, ``features.get("range")``, ``{**features, "doa": df}``), which every
consumer also still accepts. The calibration read back from disk is
``calib.pipeline.formats.results.Calibration``.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, fields, replace as _replace
from functools import cache
from typing import Any

import pandas as pd

# the keys of a features mapping that are not measurement tables
_NOT_TABLES = ("meta", "events")


@dataclass(frozen=True, eq=False)
class Features(Mapping):
    """The measurements of one session (docs/formats.md section 2; SI units, degrees only where named).

    meta : meta.json as a dict: ``speed_of_sound`` (m/s), ``reference_array``, ``arrays`` (names, N),
        the measurement sigmas (``sigma_tdoa`` s, ``sigma_doa_deg`` deg per tangent axis, ``sigma_odo`` m;
        keys of ``calib.kinds``), and the optional keys of docs/formats.md.
    events : DataFrame, one row per event (K): ``event`` (id), ``t_emit`` (s, emitter clock), ``odom_x``,
        ``odom_y``, ``odom_z`` (m, cumulative odometry in the odometry frame).
    tables : {table name: DataFrame} of the measurement tables (``calib.kinds.tables()``): ``tdoa_m``
        (event, array, tdoa s: array minus reference), ``tdoa_s`` (array, from_event, to_event, tdoa s),
        ``doa`` (event, array, ux, uy, uz: unit vector in the array frame [, sigma_deg]), and a registered
        kind's own table; absent = no such measurements.

    From a features folder: ``calib.pipeline.formats.io.read_features(folder)``; back to one:
    ``calib.pipeline.formats.io.write_features(folder, features)``. From / to the dict form:
    :meth:`from_dict`, :meth:`to_dict` (or ``dict(features)``).
    """
    meta: dict
    events: pd.DataFrame
    tables: Mapping[str, pd.DataFrame]

    def __post_init__(self):
        object.__setattr__(self, "meta", dict(self.meta))
        object.__setattr__(self, "tables", dict(self.tables))

    def __getitem__(self, key: str) -> Any:
        if key == "meta":
            return self.meta
        if key == "events":
            return self.events
        return self.tables[key]

    def __iter__(self) -> Iterator[str]:
        yield from _NOT_TABLES
        yield from self.tables

    def __len__(self) -> int:
        return len(_NOT_TABLES) + len(self.tables)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Features:
        """A record from the dict form {"meta": dict, "events": df, table name: df, ...}."""
        return cls(d["meta"], d["events"], {k: v for k, v in d.items() if k not in _NOT_TABLES})

    def to_dict(self) -> dict[str, Any]:
        """The dict form (the same objects, not copies)."""
        return dict(self)

    def replace(self, **changes: Any) -> Features:
        """A copy with ``changes`` by key (``meta``, ``events`` or a table name; a table given as None is
        left out)."""
        d = {**self, **changes}
        return Features.from_dict({k: v for k, v in d.items() if v is not None})


class Record(Mapping):
    """A frozen dataclass that reads like the dict form of earlier versions: its fields by name, a field that is
    None not a key (``record["arrays"]``, ``.get``, ``{**record}``, ``dict(record)``)."""

    def __getitem__(self, key: str) -> Any:
        if key not in _names(type(self)) or getattr(self, key) is None:
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self) -> Iterator[str]:
        return (k for k in _names(type(self)) if getattr(self, k) is not None)

    def __len__(self) -> int:
        return sum(1 for _ in self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Any:
        """A record from the dict form (the keys of the fields; those absent are None)."""
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        """The dict form (the same objects, not copies)."""
        return dict(self)

    def replace(self: Any, **changes: Any) -> Any:
        """A copy with ``changes`` (field names)."""
        return _replace(self, **changes)


@cache
def _names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls))


@dataclass(frozen=True, eq=False)
class Session(Record):
    """A recording session as ``calib.pipeline.formats.session.read_session(folder)`` reads it from its folder
    (session.toml, events.csv, the WAVs; docs/formats.md section 1), validated; what the frontend takes.

    dir : the session folder (Path). speed_of_sound : m/s. reference_array : its name.
    chirp : {"f0", "f1" (Hz), "duration" (s), "reference" (recorded chirp file or None), "kind", "fade"}.
    noise : the sigmas session.toml states ({key of ``calib.kinds``: value}, only those given).
    arrays : one dict per array: "name", "wav" / "files" and "channels" (its audio), "mics" ((M, 3) m, array
        frame), "doa_hemisphere". robot : {"speaker_offset": (3,) m} (only the keys given).
    events : DataFrame, one row per event: event, t_emit (s), odometry and the speaker's positions (m).
    temperature : °C, or None when session.toml gives none (then absent as a key).

    Frozen, and reads like the dict form of earlier versions (``session["arrays"]``, ``session.get(...)``),
    which the frontend also still accepts.
    """
    dir: Any
    speed_of_sound: float
    reference_array: str
    chirp: dict
    noise: dict
    arrays: list
    robot: dict
    events: pd.DataFrame
    temperature: float | None = None
