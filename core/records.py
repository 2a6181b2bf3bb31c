"""Typed records that cross stages (frontend or simulator → files → estimator).

:class:`Features` is the measurements of one session, docs/formats.md section 2. It is frozen (its fields
cannot be re-bound; a changed copy is :meth:`Features.replace`) and reads like the dict earlier versions
passed around (``features["doa"]``, ``features.get("range")``, ``{**features, "doa": df}``), which every
consumer also still accepts. The calibration read back from disk is
``calib.pipeline.formats.results.Calibration``.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
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
