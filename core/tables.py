"""Plain-array views of DataFrame columns, and the names of the columns and metrics the tables show (one place)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

# The readers (calib.pipeline.formats.io) add each row's line in its CSV file (header = 1) under this column, so
# outliers can be reported by file line; it lives in memory only and is never written.
LINE_COLUMN = "csv_line"

# metric key, label, scale from SI, unit: one place for how metrics are named and shown
METRIC_ROWS = (
    ("position_rmse_m", "array position RMSE", 100.0, "cm"),
    ("orientation_geodesic_deg", "orientation RMS (geodesic)", 1.0, "deg"),
    ("orientation_paper_deg", "orientation RMS (paper metric)", 1.0, "deg"),
    ("axis_rms_deg", "axis direction RMS (linear arrays, mic pairs)", 1.0, "deg"),
    ("offset_rmse_s", "offset RMSE", 1e6, "µs"),
    ("drift_rmse", "drift RMSE", 1e6, "ppm"),
    ("relative_drift_rmse", "drift RMSE relative to reference", 1e6, "ppm"),
    ("source_rmse_m", "source position RMSE", 100.0, "cm"),
)


@dataclass(frozen=True)
class ArrayParam:
    """A per-array parameter, declared once (docs/architecture.md, "Adding a per-array parameter"): ``key`` its
    field in the estimator's ``Layout``, std dict and ``State`` (``state``: ``R`` for a rotation), ``label`` its
    name in report.json ``undetermined`` and messages, ``columns`` its arrays.csv columns, ``components`` its
    components per array (a rotation's: tangent-space, about the array's own axes) with 1-σ columns
    ``<component>_std`` (docs/formats.md section 3), ``unit`` (SI); ``rotation``: on SO(3) (state (N, 3, 3),
    identity at the start, columns a scalar-first quaternion, step R Exp(φ)), else additive with ``default``
    at the start and where a table has none; ``reference``: the reference array's value "fixed" (it defines
    the frame or the time origin), "free", or free when this kind has rows (the drift: TDOA-S);
    ``can_freeze``: the observability check may leave it out of a solve when the data do not determine it."""
    key: str
    label: str
    columns: tuple
    components: tuple
    unit: str = ""
    rotation: bool = False
    default: float = 0.0
    reference: str = "fixed"
    can_freeze: bool = True

    @property
    def std_columns(self):
        return tuple(f"{c}_std" for c in self.components)

    @property
    def state(self):
        return "R" if self.rotation else self.key

    def shape(self, n):
        """Its layout block's shape for ``n`` arrays (an additive one's state block too)."""
        return (n,) if len(self.components) == 1 else (n, len(self.components))


# The per-array parameters in the arrays table's order: every list of them (the estimator's state, layout and
# step, arrays.csv's and the std columns, undetermined parameters, covariance labels) loops over this; a new
# one is appended (its factors read ``st.<key>``, ``lay.<key>``).
ARRAY_PARAMS = [ArrayParam("x", "position", ("x", "y", "z"), ("x", "y", "z"), "m"),
                ArrayParam("rot", "orientation", ("qw", "qx", "qy", "qz"), ("rx", "ry", "rz"), "rad", rotation=True),
                ArrayParam("offset", "offset", ("offset",), ("offset",), "s"),
                ArrayParam("drift", "drift", ("drift",), ("drift",), "1", reference="tdoa_s")]
ARRAYS_COLUMNS = ("array", *(c for a in ARRAY_PARAMS for c in a.columns))   # arrays.csv (calibration, truth)
SHOWN_PARAMS = frozenset(a.key for a in ARRAY_PARAMS)   # the arrays tables show these in their own units ...


def extra_array_params():
    """... and every parameter registered beyond them as its own columns, in SI units (``value ± std``)."""
    return [a for a in ARRAY_PARAMS if a.key not in SHOWN_PARAMS]


def extra_param_cells(row, a):
    """One registered parameter's components of an arrays-table ``row`` (mapping): "value ± std" each, SI."""
    def cell(c, sd):
        v, e = float(row.get(c, float("nan"))), float(row.get(sd, float("nan")))
        return f"{v:.4g}" + (f" ± {e:.2g}" if e == e else "")
    return [cell(c, sd) for c, sd in zip(a.columns, a.std_columns)]


def array_param(name):
    """The :class:`ArrayParam` of layout key or report label ``name``."""
    return next(a for a in ARRAY_PARAMS if name in (a.key, a.label))


def columns(df, names):
    """The float (n, k) matrix of the columns ``names`` of DataFrame ``df``, taken one column at a time.

    The same values as ``df[names].to_numpy(float)``, ~5x cheaper on small tables (a multi-column
    selection builds a new frame first: ~130 µs; the Monte-Carlo study scores every run and stage).
    """
    return np.column_stack([df[c].to_numpy(float) for c in names]) if len(names) else np.zeros((len(df), 0))


def flag_text(df):
    """The ``flag`` column of a features table as a str Series (a missing cell: ""; no column: "" on every row).

    An all-empty column reads as float NaN, and pandas warns on ``fillna("")`` of a float column, so the
    missing cells are replaced on an object view instead.
    """
    if "flag" not in df.columns:
        return pd.Series("", index=df.index, dtype=object)
    f = df["flag"]
    return f.astype(object).where(f.notna(), "").astype(str)


def has_flag(df, flags):
    """(rows,) bool: the row's ``flag`` (doubts joined by "+") holds one of ``flags`` (names)."""
    if "flag" not in df.columns:
        return np.zeros(len(df), bool)
    pattern = r"(?:^|\+)(?:" + "|".join(flags) + r")(?:\+|$)"
    return flag_text(df).str.contains(pattern).to_numpy(bool)


VELOCITY_COLUMNS = ("vel_x", "vel_y", "vel_z")   # events.csv, optional: the source's velocity during the sweep


def event_velocities(events):
    """(K, 3) source velocity at each event (m/s, odometry axes) from events.csv's optional ``vel_x, vel_y,
    vel_z`` (docs/formats.md; empty cells = 0), or None when the events do not carry them."""
    if not all(k in events.columns for k in VELOCITY_COLUMNS):
        return None
    v = columns(events, VELOCITY_COLUMNS)
    return np.where(np.isfinite(v), v, 0.0)
