"""The numeric problem: features (``calib.records.Features`` or the dict form) → an immutable :class:`Problem`,
and the state ↔ parameter-vector layout.

A :class:`Problem` (built once per data set) holds the arrays' names and reference, the events (emission
times, cumulative odometry), one block of rows per measurement kind (:class:`TdoaMRows`, :class:`TdoaSRows`,
:class:`DoaRows`, :class:`ConeRows`), the sigmas by measurement kind (``sigma``: the names of
``factors.KINDS``) and per-array facts (mirror folds, cone axes, which orientations are estimated).

A :class:`State` holds the unknowns (positions, rotations, clocks, sources, emission corrections, the
odometry frame's yaw); a :class:`Layout` says which of them are free in a solve and where they sit in the
parameter vector.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType, SimpleNamespace
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.kinds import KINDS
from calib.geometry import doa_covariance, fold, mic_geometry
from calib.tables import ARRAY_PARAMS, LINE_COLUMN, columns, flag_text, has_flag


def frozen_array(a):
    """A read-only view of ``a`` (no copy; the caller's array keeps its own flag): measured data that no
    stage may rewrite in place (an attempt raises ``ValueError: assignment destination is read-only``)."""
    if not isinstance(a, np.ndarray):
        return a
    v = a.view()
    v.flags.writeable = False
    return v


def frozen_arrays(d):
    """A read-only mapping of read-only views of ``d``'s arrays (other values as they are)."""
    return MappingProxyType({k: frozen_array(v) for k, v in d.items()})


@dataclass(frozen=True, eq=False)
class Rows:
    """The rows of one measurement kind: every field is an array with one entry (or row) per measurement;
    ``row`` is the measurement's line in its CSV file (header = line 1), for reports. Immutable: the fields
    are read-only views (a changed copy is ``dataclasses.replace(rows, ...)`` or :meth:`select`)."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, frozen_array(getattr(self, f.name)))

    def __setstate__(self, state):   # (unpickled arrays come back writeable: frozen again)
        self.__dict__.update(state)
        self.__post_init__()

    def __len__(self):
        return len(self.row)

    @property
    def event(self):
        """The event index of each measurement (the one it is reported at)."""
        return self.ev

    def select(self, keep):
        """The rows where the boolean (n,) ``keep`` is True (or at the integer indices ``keep``)."""
        return dataclasses.replace(self, **{f.name: getattr(self, f.name)[keep] for f in dataclasses.fields(self)
                                            if getattr(self, f.name) is not None})


@dataclass(frozen=True, eq=False)
class TdoaMRows(Rows):
    """TDOA-M: array ``arr`` vs the reference at event ``ev`` (indices), value ``val`` (s); ``scale`` (n,): each
    row's sigma relative to the type's (:func:`arrival_scales`; ones without meta ``sigma_arrival_per_array``)."""
    ev: np.ndarray
    arr: np.ndarray
    val: np.ndarray
    row: np.ndarray
    scale: np.ndarray


@dataclass(frozen=True, eq=False)
class TdoaSRows(Rows):
    """TDOA-S: array ``arr`` between events ``a`` and ``b`` (indices), value ``val`` (s); ``scale`` (n,) as in
    :class:`TdoaMRows`."""
    arr: np.ndarray
    a: np.ndarray
    b: np.ndarray
    val: np.ndarray
    row: np.ndarray
    scale: np.ndarray

    @property
    def event(self):
        return self.b


@dataclass(frozen=True, eq=False)
class DoaRows(Rows):
    """DOA: unit vector ``u`` (n, 3) in array ``arr``'s frame toward the source of event ``ev``; ``scale``
    (n,): each row's sigma relative to the type's (:func:`doa_row_scales`); ``axes`` (n, 3, 3): per row the
    unit vectors (as rows) its residual is whitened along, ``axis_scale`` (n, 3) the sigma along each relative
    to the row's (:func:`doa_axes`; identity / ones: isotropic)."""
    ev: np.ndarray
    arr: np.ndarray
    u: np.ndarray
    row: np.ndarray
    scale: np.ndarray
    axes: np.ndarray
    axis_scale: np.ndarray
    reflection: np.ndarray | None = None   # (n,) bool: doa.csv flags the row ``doa_reflection`` (None: unknown)


@dataclass(frozen=True, eq=False)
class ConeRows(Rows):
    """Cone DOA of a linear array / 2-mic pair: cos of the angle between its axis and the source."""
    ev: np.ndarray
    arr: np.ndarray
    cos: np.ndarray
    row: np.ndarray
    reflection: np.ndarray | None = None   # (n,) bool: doa.csv flags the row ``doa_reflection`` (None: unknown)


@dataclass(frozen=True, eq=False)
class Problem:
    """One calibration problem: what was measured, and the settings of a solve. Shapes: N arrays, K events;
    SI units (s, m, rad).

    Immutable: every array is a read-only view, every mapping read-only; a stage that changes a setting
    returns a new problem (:meth:`replace`, :meth:`with_weights`), so its input stays as it was.

    Measured (fixed once built): names (N,), ref the reference array's index, c (m/s), beta (s per unit
    drift: the matched filter's drift bias), t (K,) emission times minus t_0, events (K,) event ids, odom
    (K, 3) cumulative odometry; the rows of each kind (``tdoa_m``, ``tdoa_s``, ``doa``, ``cone``, and
    ``extra_rows``: {kind: Rows} of the kinds registered beyond these, ``factors.register``);
    fold (N, 3): mic-plane normal of arrays whose DOAs are mirror-ambiguous (zeros elsewhere); plane (N, 3):
    mic-plane normal of every planar array (meta ``mics``, else ``fold``; zeros elsewhere; None: none known),
    whose DOAs' in-plane part scales with the speed of sound (factors.doa);
    cone_axis (N, 3) and rot_fixed_axis (N,): a linear array's axis and the rotation component about it
    (not observable; -1 for other arrays); rot_free (N,): orientation estimated; n_doa_events (N,);
    arrival_scale (N,): each array's arrival sigma relative to the type's (:func:`arrival_scales`; None: ones).

    Settings of a solve (typed values a stage replaces, never edits): sigma {kind: sigma} for ``tdoa_s``,
    ``tdoa_m`` (s), ``doa``, ``cone`` (rad per tangent axis), ``odometry`` (m per axis per step),
    ``emission`` (s; 0 = emission times not estimated); array_scale {kind: (N,) sigma factor of each array},
    array_own {kind: (N,) bool, the array has its own component}: per-array variance components (opt-in,
    estimator/arraynoise.py; the three together: :class:`Weights`); odo_yaw_free: the odometry frame's yaw
    is estimated, odo_yaw_test: the test that decided it; fixed_cols {layout field: (shape of that field)
    bool} the columns the data leave undetermined (left out of the solve) and unobservable (one report
    entry per (array, parameter)): estimator/observability.py; motion: a source moving during the
    sweep (:class:`SourceMotion`, set by ``motion.motion_solve``; None: a stopped one): its arrival shifts in
    the TDOA factors, and its velocity error as a nuisance per event (``State.dv``, :func:`velocity_error`)
    with its prior (kind ``velocity``).
    """
    names: np.ndarray
    ref: int
    c: float
    beta: float
    t: np.ndarray
    events: np.ndarray
    odom: np.ndarray
    tdoa_m: TdoaMRows
    tdoa_s: TdoaSRows
    doa: DoaRows
    cone: ConeRows
    sigma: Mapping[str, float]
    fold: np.ndarray
    cone_axis: np.ndarray
    rot_fixed_axis: np.ndarray
    rot_free: np.ndarray
    n_doa_events: np.ndarray
    extra_rows: Mapping[str, Rows] = dataclasses.field(default_factory=dict)
    odo_yaw_free: bool = False
    odo_yaw_test: Mapping[str, Any] | None = None
    array_scale: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    array_own: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    fixed_cols: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    unobservable: tuple = ()
    arrival_scale: np.ndarray | None = None
    motion: Any = None
    c_free: bool = False
    c_test: Mapping[str, Any] | None = None
    plane: np.ndarray | None = None

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = frozen_array(v)
            elif f.name in _ARRAY_MAPS:
                v = frozen_arrays(v)
            elif f.name in ("sigma", "extra_rows", "odo_yaw_test", "c_test") and v is not None:
                v = MappingProxyType(dict(v))
            elif f.name == "unobservable":
                v = tuple(v)
            object.__setattr__(self, f.name, v)

    def __getstate__(self):   # (a read-only mapping does not pickle: its dict does)
        return {k: dict(v) if isinstance(v, MappingProxyType) else v for k, v in self.__dict__.items()}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.__post_init__()

    @property
    def N(self):
        return len(self.names)

    @property
    def K(self):
        return len(self.events)

    def rows(self, kind):
        """The measurement rows of ``kind`` (tdoa_m, tdoa_s, doa, cone, or a registered kind's)."""
        return self.extra_rows[kind] if kind in self.extra_rows else getattr(self, kind)

    def replace(self, **changes):
        """A new problem with ``changes`` (every other field shared: nothing in a problem is changed in place)."""
        return dataclasses.replace(self, **changes)

    def weights(self):
        """A working copy (:class:`Weights`) of the sigmas and per-array components, for a stage that
        re-weights; :meth:`with_weights` turns it back into a problem."""
        return Weights(dict(self.sigma), {k: v.copy() for k, v in self.array_scale.items()},
                       {k: v.copy() for k, v in self.array_own.items()})

    def with_weights(self, w):
        """A new problem weighted by ``w`` (:class:`Weights`; its arrays are copied, so ``w`` may go on changing)."""
        return self.replace(sigma=dict(w.sigma), array_scale={k: v.copy() for k, v in w.array_scale.items()},
                            array_own={k: v.copy() for k, v in w.array_own.items()})


_ARRAY_MAPS = ("array_scale", "array_own", "fixed_cols")


@dataclass(frozen=True, eq=False)
class SourceMotion:
    """A source that moves during the sweep, as the solve models it (estimator/motion.py): the arrivals of
    event j at array i are shifted by β ṙ_ij / c (or the frontend's measured ``curve`` (stretch, shift_s) at
    ε = ṙ/c), ṙ taken at the current state from the source displaced by ``disp`` (K, 3) moving at ``vel``
    (K, 3; both odometry axes, turned by the odometry yaw) — inside the factors, with its derivative. The
    velocity has an error of ``sigma`` m/s per axis (0: not modelled), which moves the arrivals as a source
    shift of ``beta`` δv and the DOAs turned from ``t_doa`` after the sweep start as one of ``t_doa`` δv."""
    vel: np.ndarray
    disp: np.ndarray
    curve: tuple | None
    beta: float
    sigma: float = 0.0
    t_doa: float = 0.0


@dataclass
class Weights:
    """The weights a variance-component stage works on (mutable, local to that stage): sigma {kind: sigma},
    array_scale {kind: (N,) factor of each array's sigma}, array_own {kind: (N,) bool, the array has its own
    component}; :meth:`Problem.with_weights` hands them to a solve."""
    sigma: dict
    array_scale: dict
    array_own: dict


@dataclass(frozen=True)
class RowIndex:
    """What a rows builder needs besides its table: array and event indices by name / id, and meta."""
    arrays: dict
    events: dict
    meta: dict

    def arr(self, names):
        """Array indices (m,) of array names."""
        return np.array([self.arrays[v] for v in names], dtype=int)

    def ev(self, ids):
        """Event indices (m,) of event ids."""
        return np.array([self.events[v] for v in ids], dtype=int)

    @staticmethod
    def lines(df):
        """The rows' lines in their CSV file (:func:`_lines`)."""
        return _lines(df)


@dataclass(frozen=True, eq=False)
class EventRows(Rows):
    """The rows of a kind measured by array ``arr`` at event ``ev`` (indices): value ``val`` (m,) or (m, k),
    the table's columns other than event and array (the default rows of a registered kind)."""
    ev: np.ndarray
    arr: np.ndarray
    val: np.ndarray
    row: np.ndarray


def event_rows(spec):
    """The default rows builder of a kind whose table is (event, array, value columns...): :class:`EventRows`."""
    values = tuple(c for c in spec.table.columns if c not in ("event", "array"))

    def build(df, ix):
        val = columns(df, values)
        return EventRows(ix.ev(df["event"]), ix.arr(df["array"]), val[:, 0] if len(values) == 1 else val, _lines(df))
    return build


def tdoa_m_rows(df, ix):
    return TdoaMRows(ix.ev(df["event"]), ix.arr(df["array"]), df["tdoa"].to_numpy(float), _lines(df), np.ones(len(df)))


def tdoa_s_rows(df, ix):
    return TdoaSRows(ix.arr(df["array"]), ix.ev(df["from_event"]), ix.ev(df["to_event"]), df["tdoa"].to_numpy(float),
                     _lines(df), np.ones(len(df)))


def doa_rows(df, ix):
    n = len(df)
    return DoaRows(ix.ev(df["event"]), ix.arr(df["array"]), columns(df, ("ux", "uy", "uz")).reshape(-1, 3), _lines(df),
                   doa_row_scales(df, ix.meta), np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), np.ones((n, 3)),
                   has_flag(df, (REFLECTION_FLAG,)))


REFLECTION_FLAG = "doa_reflection"   # the frontend's doubt: a reflection close behind the direct path shaped the DOA


def build_problem(features, *, use_tdoa_s=True, use_tdoa_m=True, use_doa=True, sigma_emit=0.0, odometry_yaw=False,
                  speed_sigma=0.0):
    """Index the measurements of a (validated) features dict → :class:`Problem`.

    Each kind with a rows builder (``factors.ROWS``) gets its rows from its features table (``use_*``: False
    leaves that kind empty); the cone rows are split from the DOA rows (meta ``doa_axes``); each kind's sigma
    comes from meta (``calib.kinds``: key and default), the emission prior's from ``sigma_emit``, the speed
    of sound's relative prior σ from ``speed_sigma`` (> 0: c may be estimated, estimator/soundspeed.py).
    """
    from .factors import ROWS   # (factors builds on this module)

    meta = features["meta"]
    names = np.asarray(meta["arrays"], dtype=object)
    idx = {n: k for k, n in enumerate(names)}
    ev = features["events"]
    events = ev["event"].to_numpy(int)
    t_emit = ev["t_emit"].to_numpy(float)
    ix = RowIndex(idx, {e: k for k, e in enumerate(events)}, meta)
    use = {"tdoa_s": use_tdoa_s, "tdoa_m": use_tdoa_m, "doa": use_doa}
    rows = {}
    for kind, build in ROWS.items():
        df = features.get(KINDS[kind].source)
        df = KINDS[kind].table.empty() if df is None else df
        rows[kind] = build(df if use.get(kind, True) else df.iloc[:0], ix)
    sigma = {k: s.sigma_si(meta) for k, s in KINDS.items() if s.noise_key}
    N = len(names)
    arrival = arrival_scales(meta, names, rows["tdoa_s"].arr)
    ref = idx[meta["reference_array"]]
    rows["tdoa_s"], rows["tdoa_m"] = scaled_tdoa_rows(rows["tdoa_s"], rows["tdoa_m"], arrival, ref)
    normals = _mirror_normals(meta, idx, N)
    doa = rows.pop("doa")
    doa, cone, cone_axis, rot_fixed_axis = _split_cones(dataclasses.replace(doa, u=fold(doa.u, normals[doa.arr])),
                                                         meta, idx, N)
    doa = doa_axes(doa, meta, names, sigma["doa"])
    # orientation estimated only for arrays with DOAs for >= MIN_DOA_EVENTS events (single microphones and
    # arrays without usable DOAs: position and clock from the TDOAs, orientation reported undetermined)
    n_doa = np.bincount(doa.arr, minlength=N)
    rot_free = (n_doa >= MIN_DOA_EVENTS) | (np.bincount(cone.arr, minlength=N) >= MIN_DOA_EVENTS)
    # a lone DOA of an array whose orientation is not estimated says nothing: leave it out
    doa = doa.select(rot_free[doa.arr] | (doa.arr == idx[meta["reference_array"]]))
    odom = columns(ev, ("odom_x", "odom_y", "odom_z"))
    return Problem(
        names=names, ref=ref, c=float(meta["speed_of_sound"]),
        beta=float(meta.get("chirp_drift_bias", 0.0) or 0.0), t=t_emit - t_emit[0], events=events, odom=odom,
        tdoa_m=rows.pop("tdoa_m"), tdoa_s=rows.pop("tdoa_s"), doa=doa, cone=cone,
        sigma={**sigma, "emission": float(sigma_emit), "speed": float(speed_sigma)}, extra_rows=rows, fold=normals,
        cone_axis=cone_axis, plane=_plane_normals(meta, names, normals),
        rot_fixed_axis=rot_fixed_axis, rot_free=rot_free, n_doa_events=n_doa,
        odo_yaw_free=bool(odometry_yaw) and odometry_yaw_observable(odom, len(doa.u), len(events)),
        arrival_scale=arrival)


MIN_DOA_EVENTS = 2   # DOAs (events) an array needs for its orientation


def _plane_normals(meta, names, mirror):
    """(N, 3): the mic-plane normal (array frame) of each planar array: from its mics in meta (``mic_geometry``),
    else its mirror normal (``mirror``, :func:`_mirror_normals`); zeros for the other arrays."""
    mics = meta.get("mics") or {}
    out = np.array(mirror, float)
    for k, name in enumerate(names):
        if len(mics.get(str(name)) or ()) >= 3:
            kind, n = mic_geometry(mics[str(name)])
            out[k] = n if kind == "planar" else 0.0
    return out


def _mirror_normals(meta, idx, N):
    """(N, 3): the mic-plane normal n (array frame) of each planar array without a stated hemisphere (meta
    ``doa_mirror_normals``), zeros elsewhere. Their DOAs are known up to the mirror image across the mic
    plane: ``build_problem`` folds them to n·u >= 0 whatever side a frontend reported."""
    out = np.zeros((N, 3))
    for name, n in (meta.get("doa_mirror_normals") or {}).items():
        out[idx[name]] = np.asarray(n, float) / np.linalg.norm(n)
    return out


# A row's own DOA sigma (doa.csv ``sigma_deg``) is shrunk this far toward the type's: scale² = (1 − w) +
# w (σ_row / σ)². It is measured from a handful of mics, so it is itself noisy: taken raw (w = 1, clipped to
# 0.3–30), the rows claiming least pulled the fit and the hall's error bars came out 1.4–1.5× too small;
# halfway, the lab's worst array went 2.76 → 1.96 cm, the hard preset's 10.5 → 5.7 cm, error / std 0.84–1.11
# (64 realistic sessions, CHANGELOG.md, 24 Nov 2026 evening)
DOA_ROW_WEIGHT = 0.5


def doa_row_scales(doa, meta):
    """Per doa.csv row, its sigma relative to the type's (``sigma_doa_deg``): from the optional per-row
    column ``sigma_deg`` (docs/formats.md; calib's frontend writes its plane-wave-fit spread there), shrunk
    (``DOA_ROW_WEIGHT``) toward the median row's (:func:`median_row_sigma`), σ_row² = (1 − w) m² + w σ_own².
    1 for rows without a value (the type's sigma: linear arrays' cone rows, 2-mic pairs) and for files
    without the column. The target is the median, not the type's sigma (the frontend's RMS of the rows): the
    rows span 100× (near-plane rows of planar arrays, a reflection's sub-band scatter) and the RMS follows the
    few largest — one unflagged 1.6° row made the hall's 0.22° over rows claiming 0.01–0.14°, 0.075° once it
    was flagged; the lab's near-plane rows made 0.48–0.70° and weighed its precise arrays' 0.06° rows as 0.34°
    (docs/results.md, issue 27)."""
    if "sigma_deg" not in doa.columns or not len(doa):
        return np.ones(len(doa))
    typical = float(meta.get("sigma_doa_deg", KINDS["doa"].noise_default))
    own = pd.to_numeric(doa["sigma_deg"], errors="coerce").to_numpy(float)
    centre = median_row_sigma(doa, own)
    centre = typical if centre is None else centre
    scale2 = ((1.0 - DOA_ROW_WEIGHT) * centre**2 + DOA_ROW_WEIGHT * own**2) / typical**2
    return np.where(np.isfinite(scale2), np.sqrt(scale2), 1.0)


def median_row_sigma(doa, own):
    """The median of the rows' own sigmas ``own`` (finite, positive) over the rows without a doubt (doa.csv
    ``flag`` empty; all rows if none is clean, or without the column); None when there are none."""
    ok = np.isfinite(own) & (own > 0)
    if "flag" in doa.columns:
        clean = ok & flag_text(doa).eq("").to_numpy()
        ok = clean if clean.any() else ok
    return float(np.median(own[ok])) if ok.any() else None


# An array's own arrival sigma (meta ``sigma_arrival_per_array``) is taken as it is, either way, from a board
# whose mics leave its arrival a residual to judge it by; a board of FEW_MICS or fewer is never taken below the
# pooled figure. The claim comes from the spread of the mics' times about the array model (constant, direction,
# wavefront curvature); a 2-mic pair's direction is its one delay, so its mics agree by construction, and a
# 4-mic board has one residual degree of freedom at most. Measured against the true geometry and clocks on
# the mixed and office presets (seeds 10–99, 261 arrays, flagged arrivals out): true / claimed arrival RMS
# median 1.0 for the 6- and 7-mic boards (quartiles 0.8–1.5), 2.2 for the 2-mic pairs (1.9–3.7), 1.2 for the
# 4-mic boards with tails to 4–14 (h35w: shrunk halfway for every low claim, the talkers' well-timed arrays
# kept 0.8 × the pool where they measure 0.3 ×). Where the data determine an array's arrivals, the estimator
# moves the scale from this prior (variance.estimate_arrival_scales).
FEW_MICS = 4


def arrival_scales(meta, names, tdoa_s_arr):
    """(N,): each array's arrival sigma relative to the pooled one, from meta ``sigma_arrival_per_array``
    ({array: s (s)}, docs/formats.md; calib's frontend writes the RMS of each array's arrival_sd): own =
    s_i / s̄ with s̄² the mean of s_i² over the TDOA-S rows ``tdoa_s_arr`` (array indices; over the arrays
    when there are none), so that the type's sigma (``sigma_tdoa``, and its variance components) still sets
    the scale; scale = own, at least 1 for boards of FEW_MICS or fewer mics (meta ``mics``; boards without
    mics in meta count as few). A TDOA-S row of array i then has sigma ∝ scale_i, a TDOA-M row
    ∝ √((scale_i² + scale_ref²) / 2). Ones without the key (today's weights); arrays missing from it get s̄."""
    N = len(names)
    given = meta.get("sigma_arrival_per_array") or {}
    s = np.array([float(given.get(str(n), np.nan)) for n in names])
    s = np.where(np.isfinite(s) & (s > 0), s, np.nan)
    if not np.any(np.isfinite(s)):
        return np.ones(N)
    over = s[tdoa_s_arr] if len(tdoa_s_arr) else s
    over = over[np.isfinite(over)]
    pool2 = float(np.mean(over**2)) if over.size else float(np.nanmean(s**2))
    own2 = np.where(np.isfinite(s), s**2 / pool2, 1.0)
    mics = meta.get("mics") or {}
    few = np.array([len(mics.get(str(n)) or ()) <= FEW_MICS for n in names])
    return np.sqrt(np.where(few, np.maximum(own2, 1.0), own2))


def scaled_tdoa_rows(tdoa_s, tdoa_m, arrival, ref):
    """(TDOA-S rows, TDOA-M rows) with each row's scale from the arrays' arrival scales ``arrival`` (N,): a TDOA-S
    row of array i ∝ a_i, a TDOA-M row ∝ √((a_i² + a_ref²) / 2) (a difference of two arrivals)."""
    return (dataclasses.replace(tdoa_s, scale=arrival[tdoa_s.arr]),
            dataclasses.replace(tdoa_m, scale=np.sqrt(0.5 * (arrival[tdoa_m.arr]**2 + arrival[ref]**2))))


def with_arrival_scale(p, arrival):
    """A new problem whose arrays' arrival scales are ``arrival`` (N,), its TDOA rows' scales to match."""
    arrival = np.asarray(arrival, float)
    tdoa_s, tdoa_m = scaled_tdoa_rows(p.tdoa_s, p.tdoa_m, arrival, p.ref)
    return p.replace(tdoa_s=tdoa_s, tdoa_m=tdoa_m, arrival_scale=arrival)


def doa_axes(doa, meta, names, sigma_doa):
    """``doa`` with each row's whitening axes and their sigmas (``DoaRows.axes``, ``axis_scale``) from the
    shape of its plane-wave fit's error covariance (``calib.geometry.doa_covariance``, meta ``mics``): the
    two principal tangent axes, the better-measured one at the row's sigma and the other at that times the
    ratio of their stds in that covariance, and the direction itself (second order in the residual) at 1.
    A planar array measures the in-plane part of a DOA; a source near its plane is then good in azimuth and
    poor in elevation (1/|u·n|, floored at √σ_doa (rad) as in the frontend's ``doa_spread``). Whitened
    alike, the elevation errors bent the arrays of the moving preset (seed 6: 2.2° RMS in elevation, 0.07°
    in azimuth, against 1.3° per axis stated). No axis is held tighter than the row's sigma: whitening them
    at RMS 1 instead (the azimuth ~√2 |u·n| of it) left fresh moving sessions no better and 3 of 6 with an
    array beyond 3σ. Arrays with fewer than 3 mics in meta (or none) stay isotropic."""
    mics = meta.get("mics") or {}
    axes, scale = np.array(doa.axes), np.array(doa.axis_scale)
    for i, name in enumerate(names):
        m = np.flatnonzero(doa.arr == i)
        if not m.size or len(mics.get(name) or ()) < 3:
            continue
        kind, normal = mic_geometry(mics[name])
        if kind not in ("planar", "volume"):
            continue
        u = doa.u[m]
        cov = doa_covariance(u, mics[name], normal, np.sqrt(sigma_doa))
        pu = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
        lam, vec = np.linalg.eigh(pu @ cov @ pu)              # ascending: [≈0 along u, tangent, tangent]
        lam = np.maximum(lam[:, 1:], 1e-12 * lam[:, 2:])
        tang = np.transpose(vec[:, :, 1:], (0, 2, 1))
        iso = lam[:, 1] <= (1.0 + ISOTROPIC_AXES_RTOL) * lam[:, 0]
        tang[iso] = canonical_tangents(u[iso], np.eye(3)[2] if normal is None else normal)
        lam[iso] = lam[iso, :1]
        axes[m] = np.concatenate([tang, u[:, None, :]], axis=1)
        scale[m] = np.column_stack([np.sqrt(lam / lam[:, :1]), np.ones(len(m))])
    return dataclasses.replace(doa, axes=axes, axis_scale=scale)


# A row whose two tangent variances are within this fraction of each other is whitened isotropically along
# :func:`canonical_tangents`: such a pair's eigenvectors are no property of the row (they turn by ~ε / gap for a
# relative input change ε: 1e-5 rad at 1e-8 here, and anywhere at all for a regular tetrahedron's exactly equal
# ones, set by rounding), while every per-component step downstream (the robust loss's weights, the residuals'
# lag correlation) reads the row in them; their stds differ by 0.05 % at most, nothing a weight tells apart
ISOTROPIC_AXES_RTOL = 1e-3
# a direction within this (rad) of the reference axis takes the array's x axis as its reference instead
CANONICAL_AXIS_MIN_SIN = 1e-6


def canonical_tangents(u, ref):
    """(n, 2, 3): per unit direction ``u`` (n, 3) its azimuth and elevation directions about the axis ``ref`` (3,,
    unit; a planar array's mic-plane normal, else the array's z): e_el the tangent toward ``ref``, e_az = e_el × u
    (the array's x axis stands in for ``ref`` within CANONICAL_AXIS_MIN_SIN of it). The basis depends on ``u``
    continuously (away from the axis), unlike the eigenvectors of an isotropic covariance."""
    u = np.asarray(u, float).reshape(-1, 3)
    ref = np.broadcast_to(np.asarray(ref, float), u.shape)
    e_el = ref - np.einsum("ka,ka->k", ref, u)[:, None] * u
    on_axis = np.linalg.norm(e_el, axis=1) < CANONICAL_AXIS_MIN_SIN
    x = np.eye(3)[0]
    e_el[on_axis] = x - (u[on_axis] @ x)[:, None] * u[on_axis]
    e_el /= np.linalg.norm(e_el, axis=1, keepdims=True)
    return np.stack([np.cross(e_el, u), e_el], axis=1)


def _split_cones(doa, meta, idx, N):
    """Move the DOA rows of arrays listed in meta ``doa_axes`` (linear arrays, 2-mic pairs) to cone rows.

    ``doa_axes``: {array: axis}, the axis a unit vector in the array frame (sign free; usually a
    coordinate axis). Such an array measures only the angle θ between its axis and the source direction;
    its doa.csv rows hold any unit vector on that cone (the estimator uses cos θ = axis · u). Returns the
    other DOA rows, the cone rows, ``cone_axis`` (N, 3) and ``rot_fixed_axis`` (N,).
    ``rot_fixed_axis`` is the array-frame coordinate axis k nearest the
    array's axis (-1 for other arrays): the rotation component about e_k is not estimated. The roll about
    the axis is not observable; the two components about the other coordinate axes move the axis in every
    direction (φ × a spans the plane ⟂ a when a_k ≠ 0), so they estimate it and fix that gauge.
    """
    cone_axis, rot_fixed_axis = np.zeros((N, 3)), -np.ones(N, int)
    for name, ax in (meta.get("doa_axes") or {}).items():
        a = np.asarray(ax, float) / np.linalg.norm(ax)
        cone_axis[idx[name]] = a
        rot_fixed_axis[idx[name]] = int(np.argmax(np.abs(a)))
    is_cone = rot_fixed_axis[doa.arr] >= 0
    d = doa.select(is_cone)
    cone = ConeRows(d.ev, d.arr, np.clip(np.einsum("ka,ka->k", cone_axis[d.arr], d.u), -1.0, 1.0), d.row,
                    d.reflection)
    return doa.select(~is_cone), cone, cone_axis, rot_fixed_axis


# The yaw of the odometry frame needs horizontal motion: a spread of the odometry across the vertical
# below this (m, RMS) leaves it to the noise.
MIN_HORIZONTAL_SPREAD = 0.05


def odometry_yaw_observable(odom, n_doa, K):
    """True when the odometry (K, 3) moves horizontally enough (and there are ``n_doa`` > 0 DOA rows) to fix
    its yaw."""
    o = odom[:, :2] - odom[:, :2].mean(0)
    return bool(n_doa > 0 and K >= 3 and np.sqrt(np.mean(np.sum(o * o, axis=1))) > MIN_HORIZONTAL_SPREAD)


def _lines(df):
    """Line numbers of the rows in their CSV file (header = line 1), or data-row positions + 2 in memory."""
    return df[LINE_COLUMN].to_numpy(int) if LINE_COLUMN in df else df.index.to_numpy(int) + 2


class State:
    """The unknowns (mutable; each solve returns a new one): the per-array parameters (``ARRAY_PARAMS``: x (N, 3)
    positions (m), R (N, 3, 3) rotations (array → reference frame), offset (N,) clock offsets (s), drift (N,)
    clock drifts, ...), s (K, 3) sources (m), e (K,) emission-time corrections (s; e[0] = 0), odo_yaw (1,) the
    odometry frame's yaw (rad), cs (1,) ln of the speed of sound over the declared one (:func:`speed`)."""

    def __init__(self, **fields: np.ndarray):
        self.__dict__.update(fields)

    def __getattr__(self, name: str) -> np.ndarray:   # (typing: the fields come from the registry)
        raise AttributeError(name)

    def __setattr__(self, name: str, value: np.ndarray) -> None:
        self.__dict__[name] = value

    def copy(self):
        return State(**{k: np.array(v, dtype=float, copy=True) for k, v in vars(self).items()})


def velocity_error(p, st):
    """(K, 3) or None: the velocity error δv of each event (m/s, reference axes) of a problem that models it
    (``p.motion``); zeros for a state that has none yet."""
    if p.motion is None or not p.motion.sigma > 0:
        return None
    dv = vars(st).get("dv")
    return np.zeros((p.K, 3)) if dv is None else dv


def speed(p, st):
    """The speed of sound (m/s) at ``st``: the declared ``p.c`` times exp(``st.cs``) (ln c / c_declared, 0 when
    c is not estimated or the state has no such field)."""
    cs = vars(st).get("cs")
    return p.c if cs is None or not len(cs) else p.c * float(np.exp(cs[0]))


def arrival_sources(p, st):
    """(K, 3) the source each event's corrected arrivals see: ``st.s``, or with a velocity error modelled
    ``st.s + β δv`` (an error δv of the correction's velocity moves the arrivals as that source shift does,
    estimator/motion.py)."""
    dv = velocity_error(p, st)
    return st.s if dv is None else st.s + p.motion.beta * dv


def empty_state(p):
    """A state for ``p.N`` arrays and ``p.K`` events: every per-array parameter at its start value (rotations
    identity), zero sources and corrections."""
    N, K = p.N, p.K
    arrays = {a.state: np.tile(np.eye(3), (N, 1, 1)) if a.rotation else np.full(a.shape(N), a.default)
              for a in ARRAY_PARAMS}
    return State(**arrays, s=np.zeros((K, 3)), e=np.zeros(K), odo_yaw=np.zeros(1), cs=np.zeros(1))


def state_from_dict(d):
    """A :class:`State` from a dict of its fields (array-like); a missing one (``odo_yaw``, a registered
    per-array parameter) at its start value."""
    blank = vars(empty_state(SimpleNamespace(N=len(d["x"]), K=len(d["s"]))))
    return State(**{k: np.array(d.get(k, v), dtype=float, copy=True) for k, v in blank.items()})


class Layout:
    """Where each free parameter sits in the parameter vector: index arrays (-1 where a parameter is fixed),
    one per block: the per-array parameters by ``key`` (``ArrayParam.shape``: x (N, 3), rot (N, 3) tangent-space
    rotation components, offset (N,), drift (N,), ...), s (K, 3), e (K,), odo_yaw (1,), dv (K, 3) a moving
    source's velocity errors (free only when the problem models them, ``Problem.motion``), cs (1,) the speed
    of sound (free when ``Problem.c_free`` and the sources are); n the number of free parameters."""

    def __init__(self, n=0, **blocks: np.ndarray):
        self.__dict__.update(blocks)
        self.n = n


def make_layout(p, *, rotations=True, ref_drift=None, emission=None, sources=True, arrays=None, odo_yaw=None):
    """Positions of the free parameters in the vector: per array its free ``ARRAY_PARAMS`` in order, then the
    sources, emission corrections and the odometry yaw. Returns a :class:`Layout` (-1 where fixed).

    The reference array's position, rotation and offset are always fixed (they define the frame and the
    time origin). Its drift is free when TDOA-S has rows (``ref_drift=None`` decides that; ``reference`` of
    its ``ArrayParam``). ``rotations=False`` fixes the rotations.
    ``arrays`` restricts the free array parameters to these indices (others are fixed).
    ``odo_yaw`` (1,): the odometry frame's yaw, free when the problem says so (``odo_yaw_free``) and the
    sources are free (``odo_yaw=None``), or as forced.
    """
    N, K = p.N, p.K
    if emission is None:
        emission = p.sigma["emission"] > 0
    free_arr = np.zeros(N, bool)
    free_arr[np.arange(N) if arrays is None else np.asarray(arrays, int)] = True
    lay = Layout(**{a.key: -np.ones(a.shape(N), int) for a in ARRAY_PARAMS}, s=-np.ones((K, 3), int),
                 e=-np.ones(K, int), odo_yaw=-np.ones(1, int), dv=-np.ones((K, 3), int), cs=-np.ones(1, int))

    def take(k):
        out = np.arange(lay.n, lay.n + k)
        lay.n += k
        return out

    for i in np.flatnonzero(free_arr):
        for a in ARRAY_PARAMS:
            comps = _free_components(p, a, i, rotations, ref_drift)
            if comps:
                getattr(lay, a.key).reshape(N, -1)[i, comps] = take(len(comps))
    if sources:
        lay.s[:] = take(3 * K).reshape(K, 3)
    if emission and K > 1:
        lay.e[1:] = take(K - 1)
    if odo_yaw is None:
        odo_yaw = bool(p.odo_yaw_free) and sources
    lay.odo_yaw = take(1) if odo_yaw else -np.ones(1, int)
    if sources and p.motion is not None and p.motion.sigma > 0:   # a moving source's velocity error: one nuisance 3-vector per event
        lay.dv[:] = take(3 * K).reshape(K, 3)
    if sources and p.c_free:   # the speed of sound: one global column, after the others (layouts without it unchanged)
        lay.cs = take(1)
    return _without_fixed(lay, p.fixed_cols)


def _free_components(p, a, i, rotations, ref_free):
    """The components of per-array parameter ``a`` of array ``i`` free in a solve (a list)."""
    if i == p.ref and a.reference != "free":
        if a.reference == "fixed" or not (len(p.rows(a.reference)) > 0 if ref_free is None else ref_free):
            return []
    if not a.rotation:
        return list(range(len(a.components)))
    if not (rotations and p.rot_free[i]):
        return []
    return [c for c in range(3) if c != p.rot_fixed_axis[i]]   # a linear array's roll: not observable


def _without_fixed(lay, fixed):
    """Drop the columns the data leave undetermined (``p.fixed_cols``: {key: bool mask shaped like that
    layout field}, set by :func:`calib.estimator.observability.check_observability`) and renumber the rest
    in order."""
    if not fixed:
        return lay
    for key, mask in fixed.items():
        setattr(lay, key, np.where(mask, -1, getattr(lay, key)))
    if lay.n == 0:  # nothing free (e.g. the reference array alone, its drift held): nothing to renumber
        return lay
    keys = [k for k in vars(lay) if k != "n"]
    used = np.zeros(lay.n, bool)
    for k in keys:
        cols = getattr(lay, k)
        used[cols[cols >= 0]] = True
    new = np.cumsum(used) - 1
    for k in keys:
        cols = getattr(lay, k)
        setattr(lay, k, np.where(cols >= 0, new[np.maximum(cols, 0)], -1))
    lay.n = int(used.sum())
    return lay


def retract(st, lay, delta):
    """Apply a parameter step ``delta`` (n,) to a state; rotations by right perturbation R Exp(φ)."""
    additive, rotated = _retract_index(lay)
    out = st.copy()
    if (lay.dv >= 0).any() and "dv" not in vars(out):   # (a state from before the velocity error was modelled)
        out.dv = np.zeros(lay.dv.shape)
    if "cs" not in vars(out):   # (a state built before the speed of sound was a field)
        out.cs = np.zeros(1)
    for key, m, cols in additive:
        if m is None:   # every entry free: the whole field, in its own order (the same sums, no masking)
            v = getattr(out, key)
            v += delta[cols].reshape(v.shape)
        else:
            getattr(out, key)[m] += delta[cols]
    for key, rows, idx, free in rotated:
        phi = delta[idx] if free is None else np.where(free, delta[idx], 0.0)
        getattr(out, key)[rows] = getattr(st, key)[rows] @ Rotation.from_rotvec(phi).as_matrix()
    return out


def _retract_index(lay):
    """Where a step lands (layout only): [(state field, its free entries (None: all), their columns)] for
    the additive fields with a free entry; [(state field, the rows of rotated arrays, their rotation columns
    (0 where fixed), which of those are free (None: all))] for the rotations with one."""
    additive, rotated = [], []
    for a in ARRAY_PARAMS:
        if a.rotation and (getattr(lay, a.key) >= 0).any():
            rows = np.flatnonzero(np.any(getattr(lay, a.key) >= 0, axis=1))
            idx = getattr(lay, a.key)[rows]
            rotated.append((a.state, rows, np.maximum(idx, 0), None if (idx >= 0).all() else idx >= 0))
    for key in [a.key for a in ARRAY_PARAMS if not a.rotation] + ["s", "e", "odo_yaw", "dv", "cs"]:
        cols = getattr(lay, key, None)
        if cols is None:   # (a layout built by hand without the field)
            continue
        m = cols >= 0
        if m.any():   # (fields without a free entry are left out; m None: all entries free)
            additive.append((key, None if m.all() else m, cols[m]))
    return additive, rotated
