"""The measurement kinds: one :class:`KindSpec` each, in one registry (``KINDS``) every layer reads.

A spec says everything calib knows about a kind apart from its maths: where its rows come from (its own
CSV :class:`Table` in features/, or the table it derives from), its noise figure (meta.json key, default,
range, report key), whether it is measured per array or per event, its degrees of freedom in the outlier
tests and which estimator stages use it. The estimator attaches the maths (factor function + rows builder,
``calib.estimator.factors.register``); readers, writers, the stage key, meta.json keys, report.json and
summary.md loop over ``KINDS``. Adding a kind: docs/architecture.md, "Adding a measurement kind".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class Table:
    """One measurement table of a features/ folder (docs/formats.md section 2), described once: the
    reader, the validation and the writer are derived from it. Columns beyond ``columns`` are kept."""
    name: str                 # <name>.csv, and the key in the features dict
    columns: tuple
    int_cols: tuple           # integer columns (event ids)
    event_cols: tuple         # columns of event ids, each must be in events.csv
    keys: tuple               # unique together, and the sort order
    float_format: str = "%.12g"
    check: Callable | None = None   # table-specific check and cleaning: (df, path, meta) -> df
    str_cols: tuple = ("array",)

    def empty(self):
        return pd.DataFrame({c: np.zeros(0, int if c in self.int_cols else str if c in self.str_cols else float)
                             for c in self.columns})


STAGES = ("ive", "joint")     # estimator stages a kind can take part in (the initialisations pick their own)


@dataclass(frozen=True)
class KindSpec:
    """Everything calib knows about one kind of measurement except its maths.

    name : key of the kind everywhere (``Problem.sigma``, report.json ``residuals``/``outliers`` types).
    table : its own CSV (a :class:`Table`; the file ``features/<table.name>.csv``), or None.
    source : the features table its rows are in (``table.name``; ``"doa"`` for the cone rows, ``"events"``
        for odometry steps, None for a prior).
    noise_key, noise_default, noise_range, noise_unit : the meta.json / session.toml key of its sigma (None:
        an option), the documented default and allowed range (lo, hi] in ``noise_unit`` ("deg" is converted
        to rad; anything else is SI). report_sigma : its key in report.json ``sigmas``.
    per_array : its rows belong to one array each (``arr``); else per event step (``-1`` array).
    dim : residuals per measurement (one CSV row; one odometry step).
    dof : degrees of freedom of one measurement in the outlier tests (None: not tested).
    reweight : variance components may re-estimate its sigma (False: a fixed prior).
    stages : the estimator stages that use it (:data:`STAGES`).
    unit, scale, label, title : report unit, the factor from SI, plot axis label and title.
    """
    name: str
    table: Table | None
    source: str | None
    unit: str
    scale: float
    label: str
    title: str
    noise_key: str | None = None
    noise_default: float = 0.0
    noise_range: tuple = (0.0, np.inf)
    noise_unit: str = "si"
    report_sigma: str | None = None
    per_array: bool = True
    dim: int = 1
    dof: int | None = None
    reweight: bool = False
    stages: tuple = ("joint",)

    @property
    def csv(self):
        """The file its rows are in, relative to the features folder (None: none)."""
        return None if self.source is None else f"{self.source}.csv"

    def sigma_si(self, meta):
        """Its sigma (SI) from a features meta dict: meta's value, else the default."""
        v = float(meta.get(self.noise_key, self.noise_default))
        return float(np.deg2rad(v)) if self.noise_unit == "deg" else v


_DEG = float(np.rad2deg(1.0))
_TDOA: dict[str, Any] = dict(noise_key="sigma_tdoa", noise_default=1e-4, noise_range=(0.0, 1.0), dof=1, reweight=True,
             stages=("ive", "joint"))
# sigma_doa_deg: the std of the DOA error along each of the two axes perpendicular to the true direction (the
# paper's code's weighting: each unit-vector residual component has std 2·sin(σ/2) ≈ σ); the paper's simulation
# rotates about an isotropic random axis by N(0, σ²), i.e. σ/√3 per axis (``pipeline.simulate.featsim`` writes so)
_DOA: dict[str, Any] = dict(noise_key="sigma_doa_deg", noise_default=5.0, noise_range=(0.0, 180.0), noise_unit="deg", reweight=True)

KINDS: dict[str, KindSpec] = {k.name: k for k in (
    KindSpec("tdoa_s", Table("tdoa_s", ("array", "from_event", "to_event", "tdoa"), ("from_event", "to_event"),
                             ("from_event", "to_event"), ("array", "from_event", "to_event")), "tdoa_s",
             "us", 1e6, "TDOA-S residual (µs)", "TDOA-S", report_sigma="tdoa_s", **_TDOA),
    KindSpec("tdoa_m", Table("tdoa_m", ("event", "array", "tdoa"), ("event",), ("event",), ("event", "array")),
             "tdoa_m", "us", 1e6, "TDOA-M residual (µs)", "TDOA-M", report_sigma="tdoa_m", **_TDOA),
    # a unit-vector residual has no noise along the direction itself: 2 degrees of freedom
    KindSpec("doa", Table("doa", ("event", "array", "ux", "uy", "uz"), ("event",), ("event",), ("event", "array"),
                          float_format="%.10g"), "doa",
             "deg", _DEG, "DOA angular error (deg)", "DOA", report_sigma="doa_rad_per_axis", dim=3, dof=2,
             stages=("ive", "joint"), **_DOA),
    KindSpec("odometry", None, "events", "cm", 100.0, "odometry residual per axis (cm)", "Odometry",
             noise_key="sigma_odo", noise_default=0.01, noise_range=(0.0, 100.0), report_sigma="odometry_m",
             per_array=False, dim=3, dof=3, reweight=True, stages=("ive", "joint")),
    KindSpec("emission", None, None, "us", 1e6, "emission-interval correction (µs)", "Emission",
             report_sigma="emission_s", per_array=False),
    # a moving source's velocity error (estimator/motion.py): one 3-vector per event, prior σ_v (m/s per axis)
    KindSpec("velocity", None, None, "mm/s", 1e3, "velocity error of the motion correction (mm/s)", "Velocity",
             per_array=False, dim=3),
    # the speed of sound's prior (estimator/soundspeed.py): ln(c / declared) ~ N(0, σ²), σ relative (an option)
    KindSpec("speed", None, None, "%", 100.0, "speed of sound against the declared one (%)", "Speed of sound",
             per_array=False),
    # cone (linear arrays, mic pairs: meta ``doa_axes``): their doa.csv rows; cosine difference ≈ rad · sin θ
    KindSpec("cone", None, "doa", "deg", _DEG, "cone (axis angle) residual, cos × 57.3 (≈ deg)", "Cone",
             report_sigma="cone_rad", dof=1, **_DOA),
)}


def register(spec):
    """Add (or replace) a kind's spec; returns it. The estimator's half: ``calib.estimator.factors.register``."""
    KINDS[spec.name] = spec
    return spec


def unregister(name):
    """Remove a registered kind (tests that register a toy kind)."""
    KINDS.pop(name, None)


def tables():
    """The CSV tables of features/ (kinds with a file of their own), in registry order."""
    return [k.table for k in KINDS.values() if k.table is not None]


def noise_keys():
    """{meta.json noise key: its (lo, hi] range}, in registry order (kinds may share a key)."""
    return {k.noise_key: k.noise_range for k in KINDS.values() if k.noise_key}

