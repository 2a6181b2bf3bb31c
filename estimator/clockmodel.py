"""Per-array clock models chosen by the evidence: steps (dropped / inserted sample blocks), drift that varies
(quadratic, piecewise linear) and wrong nominal rates (docs/method.md, "Clock models").

The base model is the linear clock of docs/architecture.md. An extra term ``h_i(t) = Σ_m c_m φ_m(t)`` per
array adds to its local arrival times (:class:`calib.clock.Clock` ``extra``), with these components φ:

* ``step`` at an interval between two events (at its middle): 1 after it, 0 before — a block of samples
  inserted (c > 0) or dropped (c < 0). It shows as one TDOA-S of +c and every TDOA-M after it shifted by c;
* ``quadratic``: u²/2 (u = t − t0): the drift changes linearly in time (c: its slope, 1/s);
* ``hinge`` at an event time h: max(0, u − h): the drift changes by c at h (piecewise-linear clock);
* ``warmup`` of time constant T: T (1 − exp(−u/T)): a drift excess c at the start relaxing as exp(−u/T) (a
  board warming up; T on a grid, WARMUP_TIME_CONSTANTS).

Selection (:func:`calibrate_clocks`), after a first robust fit (the sources and the other arrays come from
all the data; a faulty array cannot bend them, the robust tests drop it): for each array, with the sources
and the reference clock of that fit fixed, a small robust (Huber) fit of its position and clock to its own
TDOA-S and TDOA-M, with each candidate component in turn (every interval's step, every event's hinge, the
quadratic, every warm-up). The best candidate is kept when its χ² drop beats the BIC penalty with the scan's multiplicity:
``max(ln n, χ²₁ quantile at FAMILY_ALPHA / (arrays × candidates))`` (false steps < FAMILY_ALPHA per session).
Kept components correct the TDOAs (:func:`correct_features`) and the session is solved again; rounds repeat
until nothing is kept. Each kept component must have a clock's structure (:func:`structure_test`: the same
size in the TDOA-S and the TDOA-M, early and late after a step, across the arrays for the reference's and
the emitter's), which reflections (a blocked line of sight: a detour changing from stop to stop) do not
have; the rows of arrays the solve dropped or the verdict names are no evidence about the others' clocks
(:func:`_distrusted`). A step with at most PERSIST_EVENTS events on one side (next to the session's start or
end) rests on those arrivals alone: it needs the array's DOAs there on the direct path and no frontend doubt
about those arrivals (:func:`clock_persistence`, :func:`direct_path`), and to keep its evidence once the best
smooth drift term is fitted (:func:`_given`). A last joint Gauss–Newton step adds the components' columns to the full Jacobian
(:func:`refine`): their sizes, their 1-σ and the array parameters' 1-σ with them (the step's uncertainty in
the error bars: the solve's own honest σ widened by it, :func:`_apply_std`).

At scale (:mod:`calib.estimator.clockscan`): no dense rows × parameters matrix; a large session's clocks are
screened on their own rows first (:func:`_screen`: cumulative sums, O(rows)) and only flagged clocks are scored
jointly; a long session's per-array fits are of the locally best candidates (:func:`_prescreen`). Rows the
frontend doubted as reflections over a block that opens or closes an array's session, off by one constant
amount, are readmitted with a step at its edge (:func:`_readmitted`) where the step persists (the array's undoubted
arrivals beyond the block, on its side, lag with it) and the block's DOAs are the direct path's (a paused robot's
reflections are late by one amount too; their DOAs point at the reflector). A seeded step whose array jumps again in
the next (or previous) interval is a chirp lost in the dropped block: that one arrival is an ``arrival`` component
(no clock term; report.json ``clock.arrays[a].arrivals``), the step sized across both (:func:`_lost_arrivals`);
it goes with its step: where the selection removes the step, the arrival is removed too (:func:`_beside_steps`).

A moving source's correction uses a velocity off by σ_v per axis (``motion.velocity_sigma``): each event's corrected
arrivals move as a source shift of β δv would, which the odometry does not follow. The scans take it as a nuisance,
not as evidence: the joint scan projects out a column per event and axis with a unit prior
(:func:`_velocity_columns`), the per-array fits (sources held) count it in each row's σ (:func:`array_data`).
Unmodelled, it made clock steps on every seed of test_motion_noise's moving scene, and the selection solved each
session dozens of times.

A fitted |drift| >= RATE_ERROR_MIN is no crystal's: the header's sample rate is wrong; it is named (with
the pair of common rates it matches, :func:`calib.clock.header_ratio`) and the calibration stays in the
drift (1 + δ = rate ratio × (1 + crystal drift)).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import itertools

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.special import chdtri, erf, erfc

from calib.clock import TERMS as CLOCK_TERMS, Clock, Step, Term, header_ratio, time_bases
from calib.options import validate_options
from calib.robust import mad_std
from calib.tables import ARRAY_PARAMS, flag_text, has_flag

from .factors import active_kinds, arrival_shifts, row_arrays
from .init import ObservabilityError
from .motion import motion_noise
from .problem import arrival_sources, velocity_error
from .uncertainty import velocity_rows

FAMILY_ALPHA = 0.002    # false-model rate per session (Bonferroni over targets × candidates × 2 tests; measured ~1 %)
HUBER_K = 2.5           # robust scale of the per-array fits, in σ
MAX_ROUNDS = 6          # detection rounds (each adds at most one component)
MAX_COMPONENTS = 4      # extra clock parameters per array at most
GN_ITERATIONS = 20
MAX_MOVE = 0.5         # m: the per-array fits' largest position update per Gauss-Newton iteration
MIN_EVENTS = 6          # fewer events: the linear clock only (nothing to test a change against)
# A clock's drift changes by a few ppm as a board warms up or the room's temperature drifts (CHiME-6: ~1-5 ppm);
# a drift term implying a larger change over the session is a geometric error (reflections) in clock guise
MAX_DRIFT_CHANGE = 20e-6
MAX_STEP = 0.5          # s: buffer under- and overruns lose or repeat ms (USB: 0.5-20 ms); larger is no clock step
# a board warming up: its drift relaxes exponentially to the crystal's (thermal time constants of minutes); the
# warm-up candidates' time constants (s), a factor 2 apart (the nearest one's shape fits any between them to a few
# % of its curvature); those beyond the session's length are the quadratic already
WARMUP_TIME_CONSTANTS = (25.0, 50.0, 100.0, 200.0, 400.0, 800.0)
RATE_ERROR_MIN = 5e-3   # |drift| beyond any crystal's (±100 ppm typical): a wrong nominal rate
RATE_MATCH_TOL = 5e-4   # a rate ratio this close to a ratio of two common rates names them
EMITTER = "(emitter)"   # models key of the emitter's own timing: the same term in every array's clock
TIE_MARGIN = 10.0       # χ²: proposals this close to the best are decided by solving with each
# ... and those within this share of a large best margin: a fault bends the fit, and a large one makes other
# clocks' proposals nearly as strong (a 2.9 ms reference step: the emitter's step 500, the reference's 437)
TIE_SHARE = 0.25
MAX_RIVALS = 3
REFIT_SIGMA = 0.1       # the joint step moved a component by more than this × its σ: solve once more
AMBIGUOUS_CHI2 = float(chdtri(1, 0.05))   # rival proposals this close (χ²) are named as the data's ambiguity
# A kept component is tested once for its structure (:func:`structure_test`): a true clock's fails this rarely
STRUCTURE_ALPHA = 1e-3
# a clock term's evidence must survive leaving out any this many consecutive events' rows (:func:`persistent_drop`):
# rendered rooms leave one or two consecutive arrivals 3-8 σ off (a reflector near a few stops), which a step
# at their edge explains; a step with fewer events than this on a side is those events' arrivals, as the data see it
PERSIST_EVENTS = 2
PERSIST_CHI2 = float(chdtri(1, STRUCTURE_ALPHA))   # the persistent χ² of a component the scan chose: one test
MAX_REJECTED = 8        # components rejected by their structure before the selection stops looking


@dataclass(frozen=True)
class Component:
    """One extra clock component of an array: ``kind`` in (step, quadratic, hinge, warmup), ``time`` (s since t0;
    the step's instant, the hinge's knot, the warm-up's time constant T; 0 for the quadratic), coefficient
    ``value`` (the warm-up's: its drift excess at t0, relaxing as exp(−u/T)) and its 1-σ."""
    kind: str
    time: float
    value: float
    std: float | None = None

    def basis(self, u):
        """φ(u) at times u (s since t0): the component with a unit coefficient."""
        u = np.asarray(u, float)
        if self.kind in ("step", "mshift"):
            return (u >= self.time).astype(float)
        if self.kind == "arrival":   # (one event's arrival off, no clock's term: :func:`_lost_arrivals`)
            return (u == self.time).astype(float)
        if self.kind == "quadratic":
            return 0.5 * u * u
        if self.kind == "warmup":
            return _warmup(u, self.time)
        return np.maximum(u - self.time, 0.0)

    def plausible(self, duration):
        """A clock could do this: a drift term changes the drift by at most MAX_DRIFT_CHANGE over ``duration``,
        a step is at most MAX_STEP."""
        if self.kind == "quadratic":
            return abs(self.value) * duration <= MAX_DRIFT_CHANGE
        if self.kind in ("hinge", "warmup"):
            return abs(self.value) <= MAX_DRIFT_CHANGE
        return bool(np.isfinite(self.value)) and abs(self.value) <= MAX_STEP

    def with_value(self, value, std=None):
        return Component(self.kind, self.time, float(value), std)


def _warmup(u, T):
    """T (1 − exp(−u/T)): the extra local time of a drift excess exp(−u/T) (u ≥ 0; linear before): calib.clock's
    ``exp`` term with a unit amplitude (one definition for the selection and the written clock)."""
    return CLOCK_TERMS["exp"][0](np.asarray(u, float), 1.0, T)


def basis_matrix(comps, u):
    """(len(u), len(comps)) φ of every component at times u, one vectorised expression per kind."""
    u = np.asarray(u, float)
    kind = np.array([c.kind for c in comps], dtype=object)
    time = np.array([c.time for c in comps], float)
    out = np.zeros((len(u), len(comps)))
    step = (kind == "step") | (kind == "mshift")
    out[:, step] = u[:, None] >= time[step][None, :]
    out[:, kind == "quadratic"] = 0.5 * (u * u)[:, None]
    hinge = kind == "hinge"
    out[:, hinge] = np.maximum(u[:, None] - time[hinge][None, :], 0.0)
    warm = kind == "warmup"
    out[:, warm] = _warmup(u[:, None], time[warm][None, :])
    arrival = kind == "arrival"
    out[:, arrival] = u[:, None] == time[arrival][None, :]
    return out


def extra(components, u):
    """h(u) = Σ c φ(u) of a list of components."""
    out = np.zeros(np.shape(u))
    for c in components:
        out = out + c.value * c.basis(u)
    return out


def as_clock(components, offset=0.0, drift=0.0, t0=0.0):
    """The :class:`calib.clock.Clock` of a linear clock plus components (steps and drift terms)."""
    steps = tuple(Step(c.time, c.value, c.std) for c in components if c.kind == "step")
    terms = tuple(Term("quadratic", {"slope": c.value}) if c.kind == "quadratic"
                  else Term("exp", {"amplitude": c.value, "time_constant": c.time}) if c.kind == "warmup"
                  else Term("hinge", {"time": c.time, "change": c.value}) for c in components
                  if c.kind not in ("step", "arrival"))   # (an arrival off is that one arrival's, not the clock's)
    return Clock(offset, drift, t0, steps, terms)


# ----------------------------------------------------------------------------------------------- features
def correct_features(features, models):
    """A copy of ``features`` with the clock components taken out of the TDOAs.

    models : {array name: [Component]}. TDOA-M of array i at event j loses h_i(t_j) and gains h_ref(t_j);
    TDOA-S of array i over (a, b) loses h_i(t_b) − h_i(t_a). The key EMITTER: the emission times are late
    by h(t) (every array's TDOA-S loses h(t_b) − h(t_a); the TDOA-M, a difference at one emission, keep
    theirs). Nothing else changes.
    """
    models = {k: v for k, v in (models or {}).items() if v}
    if not models:
        return features
    ev = features["events"]
    t0 = float(ev["t_emit"].iloc[0])
    u_of = dict(zip(ev["event"].to_numpy(int), ev["t_emit"].to_numpy(float) - t0))
    ref = features["meta"]["reference_array"]
    out = dict(features)
    tm = features["tdoa_m"].copy()
    u = np.array([u_of[e] for e in tm["event"].to_numpy(int)])
    corr = np.zeros(len(tm))
    for name, comps in models.items():
        if name == EMITTER:
            continue   # the emission times' error is common to both arrays of a TDOA-M
        if name == ref:
            corr -= extra(comps, u)
        else:
            corr += np.where(tm["array"].to_numpy() == name, extra(comps, u), 0.0)
    tm["tdoa"] = tm["tdoa"].to_numpy(float) - corr
    ts = features["tdoa_s"].copy()
    ua = np.array([u_of[e] for e in ts["from_event"].to_numpy(int)])
    ub = np.array([u_of[e] for e in ts["to_event"].to_numpy(int)])
    corr = np.zeros(len(ts))
    for name, comps in models.items():
        mine = np.ones(len(ts), bool) if name == EMITTER else ts["array"].to_numpy() == name
        corr += np.where(mine, extra(comps, ub) - extra(comps, ua), 0.0)
    ts["tdoa"] = ts["tdoa"].to_numpy(float) - corr
    out["tdoa_m"], out["tdoa_s"] = tm, ts
    return out


# ----------------------------------------------------------------------------------------------- per-array fits
@dataclass
class ArrayData:
    """One array's TDOAs with everything else fixed at a fit: TDOA-S rows (event indices a, b, value zs),
    TDOA-M rows as local arrival times (event j, ym = TDOA-M + the reference's predicted arrival), the
    sources s (K, 3), event times u (K,) and t (K, + emission corrections), c, β, the σs; ``ref``: the
    reference array (its TDOA-S only, its position fixed at the origin)."""
    a: np.ndarray
    b: np.ndarray
    zs: np.ndarray
    j: np.ndarray
    ym: np.ndarray
    s: np.ndarray
    u: np.ndarray
    t: np.ndarray
    c: float
    beta: float
    sig_s: float | np.ndarray   # (per row with a moving source's velocity error: :func:`array_data`)
    sig_m: float | np.ndarray
    ref: bool
    floor: float = 1.0          # the smallest robust scale of the whitened rows: :func:`array_data`

    @property
    def n(self):
        return len(self.zs) + len(self.ym)


def array_data(p, st, i, velocity_sd=0.0):
    """:class:`ArrayData` of array i at the state ``st`` of problem ``p``. ``velocity_sd`` (s, β σ_v / c:
    :func:`velocity_arrival_sd`): a moving source's velocity error, which moves each event's corrected arrivals
    as a source shift of β δv does; the sources held here cannot take it up, so it is each row's noise too: a
    TDOA-S row's two arrivals' (independent events: √2 of it), a TDOA-M row's along its two directions. A
    problem that models the motion (``p.motion``) gives the rows freed of its arrival shifts at ``st`` and the
    sources its arrivals see (``s + β δv``, the velocity error as the joint fit estimated it)."""
    ms = p.tdoa_s.arr == i
    t = p.t + st.e
    sh = arrival_shifts(p, st)
    sh = np.zeros((p.N, p.K)) if sh is None else sh.sh
    src = arrival_sources(p, st)
    sig_s, sig_m = p.sigma["tdoa_s"], p.sigma["tdoa_m"]
    if velocity_sd > 0:
        sig_s = np.full(int(ms.sum()), float(np.hypot(sig_s, np.sqrt(2.0) * velocity_sd)))
    if i != p.ref:
        mm = p.tdoa_m.arr == i
        j = p.tdoa_m.ev[mm]
        d0 = np.linalg.norm(src[j] - st.x[p.ref], axis=1)
        aref = (1 + st.drift[p.ref]) * (t[j] + d0 / p.c) + st.offset[p.ref] + p.beta * st.drift[p.ref]
        ym = p.tdoa_m.val[mm] + aref
        if p.motion is not None:
            ym = ym - (sh[i, j] - sh[p.ref, j])
        if velocity_sd > 0:
            w = src[j] - st.x[i]
            du = w / np.linalg.norm(w, axis=1)[:, None] - (src[j] - st.x[p.ref]) / d0[:, None]
            sig_m = np.hypot(sig_m, velocity_sd * np.linalg.norm(du, axis=1))
    else:
        j, ym = np.zeros(0, int), np.zeros(0)
    a, b, zs = p.tdoa_s.a[ms], p.tdoa_s.b[ms], p.tdoa_s.val[ms]
    if p.motion is not None:
        zs = zs - (sh[i, b] - sh[i, a])
    return ArrayData(a, b, zs, j, ym, src, p.t, t, p.c, p.beta, sig_s, sig_m, i == p.ref,
                     _velocity_floor(p, sig_s, sig_m))


def _velocity_floor(p, sig_s, sig_m):
    """The scale below which the per-array scan's whitened rows do not go: 1 (their σ as stated), or with a moving
    source's velocity error in their σ the rows' stated σ over it (median). That error is a prior: the sources
    held at the joint fit moved with each event's β δv where the odometry and the DOAs let them, so what is left
    of it in the rows is the robust spread of their residuals (:func:`best_component`'s scale), not the prior
    (test_motion_noise's moving scene: residuals at 0.2-0.4 of it; scored in the prior, a 0.5 ms step on a dropped
    array made χ² 1.5, in its rows' own spread 30: proposed in its interval at −0.54 ms)."""
    ratio = [np.broadcast_to(p.sigma[k], np.shape(v)) / np.asarray(v, float)
             for k, v in (("tdoa_s", sig_s), ("tdoa_m", sig_m)) if np.ndim(v)]
    ratio = np.concatenate([r.ravel() for r in ratio]) if ratio else np.zeros(0)
    return float(min(1.0, np.median(ratio))) if len(ratio) else 1.0


def velocity_arrival_sd(result):
    """β σ_v / c (s): the error of a corrected arrival per unit of its direction that the velocity error of a
    moving source's correction makes (``motion.velocity_sigma``, the solve's stages ``motion``); 0 without a
    correction."""
    if velocity_error(result["problem"], result["state"]) is not None:
        return 0.0   # (the joint fit estimated each event's error: its arrival sources carry it)
    noise = motion_noise(_motion_record(result), result["problem"])
    return 0.0 if noise is None else noise.beta * noise.sigma / float(result["problem"].c)


def _motion_record(result):
    """The solve's stages ``motion`` record (``motion.motion_solve``), {} without one."""
    stages = (result.get("report") or {}).get("stages") or result.get("stages") or {}
    return stages.get("motion") or {}


def _design(D, comps):
    """Basis columns of components on the TDOA-S rows (φ(u_b) − φ(u_a)) and TDOA-M rows (φ(u_j))."""
    if not comps:
        return np.zeros((len(D.zs), 0)), np.zeros((len(D.ym), 0))
    # an "mshift" (the reference's step seen from this array: its TDOA-M shift, no TDOA-S jump) has no TDOA-S part
    S = (basis_matrix(comps, D.u[D.b]) - basis_matrix(comps, D.u[D.a])) * np.array([c.kind != "mshift" for c in comps])
    M = basis_matrix(comps, D.u[D.j])
    return S, M


def _residuals(D, x, g, tau, coef, PS, PM):
    """Whitened residuals (model − data) and Jacobian columns [x (3), g, τ, coef...] of one array."""
    ws = D.s[D.b] - x
    wa = D.s[D.a] - x
    db, da = np.linalg.norm(ws, axis=1), np.linalg.norm(wa, axis=1)
    h = D.t[D.b] - D.t[D.a] + (db - da) / D.c
    rs = (g * h + PS @ coef - D.zs) / D.sig_s
    Js = np.column_stack([-(g / D.c) * (ws / db[:, None] - wa / da[:, None]), h, np.zeros(len(h)), PS]) / np.reshape(D.sig_s, (-1, 1))
    wm = D.s[D.j] - x
    dm = np.linalg.norm(wm, axis=1)
    tm = D.t[D.j] + dm / D.c
    rm = (g * tm + tau + D.beta * (g - 1) + PM @ coef - D.ym) / D.sig_m
    Jm = np.column_stack([-(g / D.c) * wm / dm[:, None], tm + D.beta, np.ones(len(tm)), PM]) / np.reshape(D.sig_m, (-1, 1))
    return np.concatenate([rs, rm]), np.vstack([Js, Jm])


def huber_rho(r, k=HUBER_K):
    a = np.abs(r)
    return np.where(a <= k, 0.5 * r * r, k * a - 0.5 * k * k)


def cauchy_rho(r, k=HUBER_K):
    """Cauchy's ρ (r²/2 near 0): a row far off costs ~k² ln|r|, so no component wins by pulling a gross
    outlier part of the way (a chirp lost in a dropped block, 600σ off: Huber pays k per σ of it)."""
    return 0.5 * k * k * np.log1p((r / k) ** 2)


def _sqrt_weights(r, loss):
    """√ of the IRLS weights of whitened residuals r: Huber's or Cauchy's (scale HUBER_K)."""
    if loss == "huber":
        return np.sqrt(np.where(np.abs(r) <= HUBER_K, 1.0, HUBER_K / np.maximum(np.abs(r), 1e-300)))
    return 1.0 / np.sqrt(1.0 + (r / HUBER_K) ** 2)


def spread(r, k=HUBER_K, iterations=3):
    """The robust scale of whitened residuals r: Huber's "proposal 2" (the RMS of the residuals clipped at k
    scales, over its value for a unit normal), from the MAD. A normal sample gets its σ; a heavy tail (a few
    arrivals off by 3-8 σ: reflections in a rendered room) widens it where the MAD does not, and a gross
    outlier counts as k scales only."""
    r = np.asarray(r, float)
    if not len(r):
        return 1.0
    s = max(1.4826 * float(np.median(np.abs(r))), 1e-300)
    kn = k * np.exp(-0.5 * k * k) / np.sqrt(2 * np.pi)
    norm = float(erf(k / np.sqrt(2.0))) - 2.0 * kn + k * k * float(erfc(k / np.sqrt(2.0)))   # E min(z², k²)
    for _ in range(iterations):
        s = float(np.sqrt(np.mean(np.minimum(r * r, (k * s) ** 2)) / norm))
    return s


def fit_array(D, comps, x0, g0, tau0, trusted=None):
    """Robust Gauss–Newton fit of one array's position (not the reference's), clock and the components'
    coefficients: Huber's loss first (convex in the clock: it converges from a pose fitted to data a large step
    contaminates, every row hundreds of σ off), then Cauchy's from there (:func:`cauchy_rho`: a gross
    outlier pulls nothing). ``trusted`` (per row, :func:`_trusted`): Huber's stage fits those rows only where
    MIN_EVENTS are (Huber's linear tail lets reflection-only arrivals ms late, most of an occluded array's rows,
    pull the pose into a basin the Cauchy stage does not leave); Cauchy's fits every row from there, so a doubted
    arrival the model fits still testifies (a step inside a run of doubted events). Returns (x, g, τ, coef,
    whitened residuals)."""
    use = (np.asarray(trusted, float) if trusted is not None and len(trusted) == D.n
           and int(np.sum(trusted)) >= MIN_EVENTS else np.ones(D.n))
    PS, PM = _design(D, comps)
    theta = np.concatenate([x0, [g0, tau0], [c.value for c in comps]]).astype(float)
    free = np.ones(len(theta), bool)
    if D.ref:
        free[:3] = False
        free[4] = False
    for loss in ("huber", "cauchy"):
        for _ in range(GN_ITERATIONS):
            r, J = _residuals(D, theta[:3], theta[3], theta[4], theta[5:], PS, PM)
            w = _sqrt_weights(r, loss) * (use if loss == "huber" else 1.0)
            A = J[:, free] * w[:, None]
            d = np.linalg.norm(A, axis=0)
            d = np.where(d > 0, d, 1.0)
            step = np.linalg.lstsq(A / d, -r * w, rcond=None)[0] / d
            move = np.linalg.norm(step[:3]) if not D.ref else 0.0
            if move > MAX_MOVE:   # a trust region: a pose metres off, its rows far from any fit, flew to 1e15 m
                step = step * (MAX_MOVE / move)
            theta[free] += step
            if np.all(np.abs(step[3:] if not D.ref else step) <= 1e-10 * (1 + np.abs(theta[free][3:] if not D.ref
                                                                                     else theta[free]))) \
                    and np.linalg.norm(step[:3] if not D.ref else 0.0) < 1e-7:
                break
    r, _ = _residuals(D, theta[:3], theta[3], theta[4], theta[5:], PS, PM)
    return theta[:3], theta[3], theta[4], theta[5:], r


def candidates(u, comps):
    """Components to test on this array: a step in every interval between consecutive event times (but those
    next to a step it has), the quadratic, a hinge at every interior event time but the last, a warm-up of each
    time constant in WARMUP_TIME_CONSTANTS within the session's length (those already in ``comps`` left out)."""
    t = np.unique(u)
    have = {(c.kind, round(c.time, 9)) for c in comps}
    # no step next to one already there: two opposite steps around one event are that event's arrival off
    near = {k + d for c in comps if c.kind == "step" for k in [int(np.searchsorted(t, c.time)) - 1] for d in (-1, 1)}
    out = [Component("step", 0.5 * (t[k] + t[k + 1]), 0.0) for k in range(len(t) - 1) if k not in near]
    # (no hinge at the last interior event: it moves only the last event, as a step in the last interval)
    out += [Component("quadratic", 0.0, 0.0)] + [Component("hinge", float(v), 0.0) for v in t[1:-2]]
    out += [Component("warmup", T, 0.0) for T in _warmups(t)]
    return [c for c in out if (c.kind, round(c.time, 9)) not in have]


def _warmups(t):
    """The warm-up time constants tested over event times t: those up to the session's length."""
    return [T for T in WARMUP_TIME_CONSTANTS if T <= np.ptp(t)] if len(t) > 1 else []


def family_sizes(u):
    """Number of candidates :func:`candidates` tests for event times u (the scans' multiplicity)."""
    k = len(np.unique(u))
    return max(k - 1, 1) + 1 + max(k - 3, 1) + len(_warmups(np.unique(u)))


def penalty(kind, n, n_arrays, n_candidates):
    """The χ² drop a new component must beat: BIC's ln n, or the χ²₁ quantile at FAMILY_ALPHA / 2 (two
    tests: :func:`best_component`, :func:`joint_scan`) over the arrays and the candidates tested on each (the
    scan's multiplicity, every kind), whichever is larger."""
    m = 2 * max(n_candidates, 1) * max(n_arrays, 1)
    return max(float(np.log(max(n, 2))), float(chdtri(1, FAMILY_ALPHA / m)))


def _key(c):
    return c.kind, round(c.time, 9)


def _trusted(D, p, name, doubted):
    """Per row of ``D`` (:func:`array_data` of array ``name`` in problem ``p``; TDOA-S rows, then TDOA-M): whether
    none of its arrivals is one the frontend doubts as the direct path's (``doubted``: :func:`doubted_arrivals`; a
    TDOA-M holds the reference's too)."""
    bad = _doubted_table(p, doubted)
    own = bad[[str(n) for n in p.names].index(name)]
    a, b, j = (np.asarray(x, int) for x in (D.a, D.b, D.j))
    return ~np.concatenate([own[a] | own[b], own[j] | bad[p.ref, j]])


def best_component(D, comps, x0, g0, tau0, n_arrays, skip=frozenset(), reference=True, free=(), trusted=None):
    """The best new component of one array and its margin over the penalty (χ²), or (None, margin <= 0).
    ``reference``: the reference's step seen from here (its TDOA-M shifted, "mshift") is a candidate too —
    not for an array the solve dropped: the reference's clock shows in every array's TDOA-M, and an array
    whose rows contradict the rest cannot say alone that the reference stepped.

    The base fit (``comps``) and each candidate's fit are robust; their χ² drop is measured in the
    residuals' own robust scale (MAD of the best candidate's whitened residuals, at least 1: a sigma stated
    too small never makes a false step; with a moving source's velocity error in the rows' σ, at least their
    stated σ's share of it: :func:`_velocity_floor`).

    ``free``: "arrival" components (one event's arrival off) fitted in every fit, base and candidates, and
    left out of the result: the arrivals the frontend doubts for a reason no clock gives (CLOCK_BLIND_DOUBTS)
    testify nothing about the clock (rendered warehouse seed 30: A4's arrivals at events 5 and 13, both behind
    an obstacle and flagged mic_spread, 0.14 ms early; two steps before them and a pose moved 4 cm fitted every
    row). ``trusted``: per row of ``D``, whether its arrivals are undoubted (:func:`_trusted`): the robust scale's
    rows."""
    if len(np.unique(D.u)) < MIN_EVENTS or D.n < MIN_EVENTS or len(comps) >= MAX_COMPONENTS:
        return None, 0.0, None
    own = len(comps)   # (the model's components, its arrivals too; the free ones after them are left out)
    comps = list(comps) + list(free)
    xb, gb, tb, cb, rb = fit_array(D, comps, x0, g0, tau0, trusted)
    base = [c.with_value(v) for c, v in zip(comps, cb)]
    cands = candidates(D.u, comps)
    if not D.ref and reference:   # the reference's step, seen from here
        cands += [Component("mshift", c.time, 0.0) for c in cands if c.kind == "step"]
    cands = [c for c in cands if _key(c) not in skip]   # (rejected by their structure: :func:`structure_test`)
    # no step next to the session's start or end: it rests on those few arrivals, which bend no fit; the joint
    # scan judges it with its persistence and direct path at once (:func:`clock_persistence`)
    cands = [c for c in cands if c.kind not in ("step", "mshift") or end_side(D.u, c.time) is None]
    tested = len(cands)
    if tested > FIT_ALL_MAX:   # a long session: robust fits of the locally best few of each kind only
        cands = _prescreen(D, base, (xb, gb, tb, cb, rb), cands)
    fits = []
    duration = float(np.ptp(D.u))
    for cand in cands:
        x, g, tau, coef, r = fit_array(D, base + [cand], xb, gb, tb, trusted)
        if np.all(np.isfinite(r)) and cand.with_value(coef[-1]).plausible(duration):
            fits.append((float(np.sum(cauchy_rho(r))), cand, coef, r))
    if not fits:
        return None, 0.0, None
    # (the MAD: this fit holds the sources where a large fault may have bent them, its rows are not clean yet; of
    # the rows whose arrivals the frontend does not doubt (``trusted``) where MIN_EVENTS are: reflection-only
    # arrivals ms late in 8 of an occluded office array's 20 events, most of its rows, made it 0.3-2 ms and the
    # scan then fitted steps to the reflections' excess paths)
    rbest = min(fits, key=lambda f: f[0])[3]
    if trusted is not None and len(trusted) == len(rbest) and trusted.sum() >= MIN_EVENTS:
        rbest = rbest[trusted]
    scale = max(D.floor, 1.4826 * float(np.median(np.abs(rbest))))
    best, by_kind = None, []
    for kind in ("step", "mshift", "quadratic", "hinge", "warmup"):
        fam = [f for f in fits if f[1].kind == kind]
        if not fam:
            continue
        cost, cand, coef, r = min(fam, key=lambda f: f[0])
        drop = 2.0 * (np.sum(cauchy_rho(rb / scale)) - np.sum(cauchy_rho(r / scale)))
        margin = drop - penalty(kind, D.n, n_arrays, len(fits) if tested <= FIT_ALL_MAX else tested)   # (Bonferroni
        # over every candidate tested, the prescreened ones too)
        by_kind.append((margin, [c.with_value(v) for m, (c, v) in enumerate(zip(base + [cand], coef))
                                 if m < own or m == len(base)]))
        if best is None or margin > best[1]:
            new = by_kind[-1][1]
            # candidates the rows cannot tell apart go to the rivals' solves (as in :func:`joint_scan`)
            tied = [[c.with_value(v) for m, (c, v) in enumerate(zip(base + [f[1]], f[2])) if m < own or m == len(base)]
                    for f in fam
                    if f[1] is not cand and abs(f[0] - cost) <= 1e-6 * max(abs(cost), 1.0)]
            best = (new, float(margin), {"chi2_drop": float(drop), "scale": scale, "kind": kind, "tied": tied})
    if best is not None and best[1] > 0:
        best[2]["kinds"] = _other_kinds(by_kind, best)
    return best


def _other_kinds(by_kind, best):
    """The proposals (components) of the best of each other kind whose margin (χ²) is within AMBIGUOUS_CHI2 of
    the ``best`` one's, best first: the evidence does not tell them from it (a warm-up, a hinge and the quadratic
    fit a drift that varies alike at a few µs: rendered lab seed 22, χ² 74.8 / 72.9 / 74.1, and the hinge, ahead
    by 0.2 after the leave-out, left the session 2.1× its fault-free error), so they are solved as rivals
    (:func:`_decide`: the one that explains every row best is kept). ``by_kind``: [(margin, components)]."""
    return [c for m, c in sorted(by_kind, key=lambda x: -x[0])
            if c is not best[0] and m > 0 and m >= best[1] - AMBIGUOUS_CHI2]


FIT_ALL_MAX = 160   # candidates: beyond, an array's robust fits are of the SCREEN_TOP best of each kind, ranked
                    # by their linearised score at the base fit (:func:`_prescreen`)


def _prescreen(D, base, fit, cands):
    """The SCREEN_TOP candidates of each kind with the largest χ² drop in the linearisation of the array's base
    fit ``fit`` (x, g, τ, coefficients, residuals; rows Cauchy-weighted at it, its parameters projected out):
    O(rows + candidates) by cumulative sums (:func:`calib.estimator.clockscan.local_scores`), so that a long
    session's per-array scan fits a few dozen candidates, not three per event."""
    from .clockscan import ClockRows, local_scores, subset

    x, g, tau, coef, r = fit
    PS, PM = _design(D, base)
    _, J = _residuals(D, x, g, tau, coef, PS, PM)
    if D.ref:
        J = np.delete(J, [0, 1, 2, 4], axis=1)
    sw = _sqrt_weights(r, "cauchy")
    nS, nM = len(D.zs), len(D.ym)
    w = sw / np.concatenate([np.broadcast_to(D.sig_s, nS), np.broadcast_to(D.sig_m, nM)])
    rows = np.arange(nS + nM)
    ends_row = np.concatenate([np.arange(nS), np.arange(nS), nS + np.arange(nM)])
    U = np.concatenate([D.u[D.b], D.u[D.a], D.u[D.j]])
    sgn = np.concatenate([np.ones(nS), -np.ones(nS), np.ones(nM)])
    far = np.concatenate([D.u[D.b], D.u[D.b], D.u[D.j]])
    span = np.concatenate([np.zeros(nS), D.u[D.b] - D.u[D.a], np.zeros(nM)])
    cr = ClockRows(rows, np.zeros(len(rows), int), w, U, sgn, ends_row, far, span)
    C = J * sw[:, None]
    score = {}
    for fam_rows, kinds in ((cr, ("step", "quadratic", "hinge")), (None, ("mshift",))):
        fam = [c for c in cands if c.kind in kinds]
        if not fam:
            continue
        sub = fam_rows if fam_rows is not None else subset(cr, rows >= nS)
        keep = slice(None) if fam_rows is not None else slice(nS, None)
        steps = [c.time for c in fam if c.kind in ("step", "mshift")]
        hinges = [c.time for c in fam if c.kind == "hinge"]
        L, _, _ = local_scores(sub, C[keep], (r * sw)[keep], steps, hinges)
        order = [c for c in fam if c.kind in ("step", "mshift")] + [Component("quadratic", 0.0, 0.0)] + \
            [c for c in fam if c.kind == "hinge"]
        score.update({_key(c): v for c, v in zip(order, L)})
    out = []
    for kind in ("step", "mshift", "quadratic", "hinge", "warmup"):   # (warm-ups: a few, all kept)
        fam = [c for c in cands if c.kind == kind]
        out += sorted(fam, key=lambda c: -score.get(_key(c), 0.0))[:SCREEN_TOP]
    return out


# ----------------------------------------------------------------------------------------------- joint scan
def _robust_weights(result, lin, p=None, own=None):
    """√ of the Huber weights of a linearisation's rows in the TDOA rows' robust scale, and that scale. The
    rows of the arrays the solve dropped as unreliable weigh nothing: their pose was fitted to them alone, the
    sources and the other arrays to the rest (what those rows say is judged per array, :func:`best_component`),
    but for array ``own``'s (a component of its own under test); so do those of the arrays the verdict names
    (:func:`_distrusted`)."""
    r = lin.r
    tdoa = np.concatenate([np.full(len(f.r), f.kind in ("tdoa_s", "tdoa_m")) for f in lin.factors])
    p = result["problem"] if p is None else p
    dropped = np.isin(row_arrays(p, lin.factors), [j for j, n in enumerate(p.names)
                                                    if str(n) in _distrusted(result) and str(n) != own])
    use = tdoa & ~dropped
    scale = max(1.0, 1.4826 * float(np.median(np.abs(r[use])))) if use.any() else 1.0
    sw = np.sqrt(np.where(np.abs(r) <= HUBER_K * scale, 1.0, HUBER_K * scale / np.maximum(np.abs(r), 1e-300)))
    return np.where(dropped, 0.0, sw), scale


def joint_scan(result, models, banned=frozenset(), stats=None, doubted=frozenset()):
    """Every array's candidates tested in the linearised joint problem at ``result`` (the sources and the
    other arrays free: what a fit absorbs by moving them is not evidence). Rows Huber-weighted (an outlier
    row cannot make a step), the χ² drop of each candidate column after projecting out the Jacobian's
    (and the existing components') columns (:class:`~calib.estimator.clockscan.Projector`), in the robust
    scale of the residuals.

    Cost: a small problem (:func:`_exact_affordable`) scores every candidate of every clock so. A larger one
    screens first (:func:`_screen`): each clock's candidates scored against its own rows with only its own
    array's parameters projected out, all at once by cumulative sums; only a clock whose best local score
    reaches SCREEN_FRACTION of its penalty has its SCREEN_TOP best candidates of each kind scored in the
    joint problem (a clean array of a large session costs O(its rows)). ``stats`` (a dict): counts of the
    clocks screened and scored (``screened``, ``scored``, ``factored``: projector factorisations). ``doubted``:
    the arrivals the frontend doubts (:func:`doubted_arrivals`: no step next to a session's end from them).

    Returns {array index: (new components as increments, margin, info)} like :func:`best_component`, or
    {} for problems too large (SCAN_MAX parameters)."""
    from .clockscan import Projector, clock_rows
    from .problem import make_layout
    from .solver import linearise

    p, st = result["problem"], result["state"]
    stats = {} if stats is None else stats
    lay = make_layout(p)
    if lay.n > SCAN_MAX:
        return {}
    lin = linearise(p, st, lay, active_kinds(p), dense=False)
    J = scipy.sparse.csr_matrix(lin.J)
    r = lin.r
    sw0, scale = _robust_weights(result, lin)
    kept = _kept_rows(result, lin.factors)
    dropped = _distrusted(result)
    zero = {name: [c.with_value(0.0) for c in comps] for name, comps in models.items()}
    E, _ = component_columns(p, lin.factors, zero)
    V = _velocity_columns(result, lin, lay)
    JE = scipy.sparse.hstack([J, scipy.sparse.csr_matrix(E)] + ([V] if V is not None else [])).tocsr()
    nuisance = np.arange(J.shape[1] + E.shape[1], JE.shape[1])
    prior = np.concatenate([np.zeros(J.shape[1] + E.shape[1]), np.ones(len(nuisance))]) if len(nuisance) else None
    local = np.setdiff1d(np.arange(JE.shape[1]), np.concatenate([lay.s.ravel(), lay.e.ravel(), lay.odo_yaw.ravel(),
                                                                 lay.dv.ravel(), nuisance]))
    exact = _exact_affordable(lay.n, len(p.t), p.N + 1)
    out, bases, cache = {}, {}, {}
    for i in range(-1, p.N):   # -1: the emitter
        name = EMITTER if i < 0 else str(p.names[i])
        have = zero.get(name, [])
        if len(have) >= MAX_COMPONENTS or len(np.unique(p.t)) < MIN_EVENTS or name in dropped:
            continue
        # rows the solve screened out are evidence about the clock that stamped them only: Huber's score gives
        # a row 600σ off its full k, and through the sources it shares it reads as the other arrays' steps (a
        # chirp lost in a dropped block made 0.14 ms "steps" of three others); its own clock's candidates
        # keep it (a 1 ms emission step screens every array's TDOA-S row of its interval)
        sw = sw0 * np.maximum(kept, _own_rows(p, lin.factors, i))
        cands = _candidates_cached(p.t, have, {k[1:] for k in banned if k[0] == name}, cache)
        cr = clock_rows(p, lin.factors, i, sw)
        if not cands or not len(cr.rows):
            continue
        stats["screened"] = stats.get("screened", 0) + 1
        tested = len(cands)   # (the scan's multiplicity: every candidate the screen looked at)
        if not exact:
            cands = _screen(p, cr, JE, local, r, sw, cands, i, scale, cache)
            if not cands:
                continue
        stats["scored"] = stats.get("scored", 0) + 1
        stats.setdefault("flagged", []).append(name)
        key = sw.tobytes()
        if key not in bases:
            stats["factored"] = stats.get("factored", 0) + 1
            pr = Projector(scipy.sparse.diags(sw) @ JE, lay, prior)
            bases = {key: (pr, pr.resid(r * sw))}   # (one kept: the next clock's weights mostly differ)
        pr, rp = bases[key]
        best = _scan_best(p, lin.factors, i, cands, have, (pr, rp, cr), sw, scale, tested, doubted)
        if best is not None:
            out[i] = best
    return out


def _velocity_columns(result, lin, lay):
    """(rows, 3K) sparse, or None without a moving source's correction: a nuisance column per event and axis,
    the velocity error of the correction (σ_v, unit prior in the scan), which moves the event's corrected
    arrivals as a source shift of β δv does: the error bars' ``uncertainty.velocity_rows``. The sources
    themselves are pinned by the odometry and the DOAs, the arrivals' shift is not: unmodelled, 3 cm of it per
    event made clock steps on every seed of test_motion_noise's moving scene. (The DOAs turn by t_doa δv, meta
    doa_time_s, not known here: left out (t_doa 0), which lets the nuisance move the arrivals' source a little
    more freely than it does.)"""
    V = velocity_rows(lin, lay, motion_noise(_motion_record(result), result["problem"]))
    return None if V is None else scipy.sparse.csr_matrix(V)


def _weighted(J, E, sw):
    """[J, E] (sparse; E dense: the components' few columns) with rows scaled by sw, as CSR."""
    JE = scipy.sparse.hstack([scipy.sparse.csr_matrix(J), scipy.sparse.csr_matrix(E)]).tocsr()
    return scipy.sparse.diags(sw) @ JE


def _with_nuisance(result, lin, lay, E, sw):
    """(A, prior): ``_weighted(lin.J, [E V], sw)`` with a moving source's velocity nuisance V
    (:func:`_velocity_columns`) after the components' columns E, and its unit prior over A's columns (None
    without V). Every joint test of a component (scan, structure, persistence, its size and σ) projects out
    the same nuisance: left in, the velocity error's arrival shifts read as misfits of the clock terms."""
    V = _velocity_columns(result, lin, lay)
    if V is None:
        return _weighted(lin.J, E, sw), None
    A = _weighted(lin.J, scipy.sparse.hstack([scipy.sparse.csr_matrix(E), V]), sw)
    return A, np.concatenate([np.zeros(lin.J.shape[1] + E.shape[1]), np.ones(V.shape[1])])


SCAN_MAX = 4000         # parameters: the joint scans and tests up to this
EXACT_FLOPS = 2e9     # a joint scan of every candidate of every clock within this many flops: no screen
SCREEN_FRACTION = 0.5   # a clock's best local score (own parameters out) below this share of its penalty: clean
SCREEN_TOP = 8          # candidates of each kind scored in the joint problem for a clock the screen flags


def _exact_affordable(n, k, clocks):
    """Whether scoring every candidate (~3 per event) of every clock in the joint problem (n parameters) costs
    at most EXACT_FLOPS (a triangular solve of n² per candidate)."""
    return float(n) * n * 3 * k * clocks <= EXACT_FLOPS


def _candidates_cached(u, have, ban, cache):
    """:func:`candidates` less the banned (kind, time) keys ``ban``: the same list object for the clocks with the
    same components (most have none), with (kinds, times) arrays for :func:`_screen` in ``cache``."""
    key = (tuple(_key(c) for c in have), frozenset(ban))
    if key not in cache:
        cands = [c for c in candidates(u, have) if not ban or _key(c) not in ban]
        cache[key] = cands
        cache[id(cands)] = (np.array([c.kind for c in cands]), np.array([c.time for c in cands], float))
    return cache[key]


def _plausible(kinds, values, duration):
    """:meth:`Component.plausible` of many candidates at once."""
    v = np.abs(values)
    return np.where(kinds == "quadratic", v * duration <= MAX_DRIFT_CHANGE,
                    np.where((kinds == "hinge") | (kinds == "warmup"), v <= MAX_DRIFT_CHANGE,
                             np.isfinite(values) & (v <= MAX_STEP)))


def _screen(p, cr, JE, local, r, sw, cands, i, scale, cache=None):
    """The candidates of clock i worth scoring in the joint problem (:func:`joint_scan`), by a local score:
    each candidate against the clock's own rows ``cr`` with its own array parameters (the columns ``local`` of
    JE: poses, clocks, components) projected out, in the clock's robust scale once its best local candidate is
    fitted. The SCREEN_TOP best of each kind whose best reaches SCREEN_FRACTION of its penalty; none when no
    kind does. Holding the sources makes this score smaller than the joint one by the share of a column the
    sources absorb (measured 0.5-0.9 with 5-20 arrays); a clock term's evidence is in its own rows (a step:
    one TDOA-S and every later TDOA-M alike; a drift change: the TDOA-M's curvature in time)."""
    from .clockscan import family_columns, local_scores, project_off

    kinds, times = (cache or {}).get(id(cands)) or (np.array([c.kind for c in cands]),
                                                     np.array([c.time for c in cands], float))
    C = scipy.sparse.diags(sw[cr.rows]) @ JE[cr.rows][:, local]
    rw = r[cr.rows] * sw[cr.rows]
    st, hi = np.flatnonzero(kinds == "step"), np.flatnonzero(kinds == "hinge")
    L, value, _ = local_scores(cr, C, rw, times[st], times[hi])
    # local_scores' order: the steps, the quadratic, the hinges
    where = np.concatenate([st, np.flatnonzero(kinds == "quadratic")[:1], hi])
    keep = np.concatenate([np.ones(len(st), bool), [bool((kinds == "quadratic").any())], np.ones(len(hi), bool)])
    L, value = L[keep], value[keep]
    warm = np.flatnonzero(kinds == "warmup")
    if warm.size:   # (a few smooth columns: projected directly, O(rows) each)
        X = project_off(cr, C, np.column_stack([family_columns(cr, [cands[k] for k in warm]), rw]))
        b, y = X[:, :-1], X[:, -1]
        nb = np.maximum(np.einsum("ij,ij->j", b, b), 1e-300)
        L, value, where = np.concatenate([L, (b.T @ y) ** 2 / nb]), np.concatenate([value, -(b.T @ y) / nb]), \
            np.concatenate([where, warm])
    L = np.where(_plausible(kinds[where], value, float(np.ptp(p.t))), L, 0.0)
    if not L.any():
        return []
    k0 = int(np.argmax(L))
    X = project_off(cr, C, np.column_stack([family_columns(cr, [cands[where[k0]]]), rw]))
    left = (X[:, 1] + value[k0] * X[:, 0]) / sw[cr.rows]
    scale_i = max(scale, spread(left))
    n = len(p.tdoa_s.val) if i < 0 else int(np.sum((p.tdoa_s.arr == i))) + int(np.sum(p.tdoa_m.arr == i))
    out = []
    for kind in ("step", "quadratic", "hinge", "warmup"):
        fam = np.flatnonzero(kinds[where] == kind)
        if fam.size and L[fam].max() / scale_i ** 2 >= SCREEN_FRACTION * penalty(kind, n, p.N + 1, len(cands)):
            out += [cands[where[k]] for k in fam[np.argsort(-L[fam])[:SCREEN_TOP]] if L[k] > 0]
    return out


def _event_rows(p, fs, rows, ids=False):
    """For each event with any of the stacked rows ``rows`` (bool mask over the factors ``fs``): the indices
    of those rows that involve it (a TDOA-M at it, a TDOA-S from or to it), in event order; ``ids``: (the
    events' indices, those lists)."""
    a, b = [], []
    for f in fs:
        n = len(f.r)
        if f.kind == "tdoa_s" and len(p.tdoa_s.a) == n:
            a.append(p.tdoa_s.a), b.append(p.tdoa_s.b)
        elif f.kind == "tdoa_m" and len(p.tdoa_m.ev) == n:
            a.append(p.tdoa_m.ev), b.append(p.tdoa_m.ev)
        else:
            a.append(np.full(n, -1)), b.append(np.full(n, -1))
    a, b = np.concatenate(a), np.concatenate(b)
    events = [int(e) for e in np.unique(np.concatenate([a[rows], b[rows]])) if e >= 0]
    groups = [np.flatnonzero(rows & ((a == e) | (b == e))) for e in events]
    return (np.array(events, int), groups) if ids else groups


def _array_rows(p, fs, rows):
    """For each array with any of the stacked rows ``rows``: the indices of those rows that are its."""
    arr = row_arrays(p, fs)
    return [np.flatnonzero(rows & (arr == a)) for a in np.unique(arr[rows]) if a >= 0]


def end_side(t, time, n_events=PERSIST_EVENTS):
    """The positions (into event times ``t``, in time order) of the events on the short side of a step at
    ``time`` when that side holds at most ``n_events`` of them (a step near a session's start or end), else
    None."""
    before = np.flatnonzero(np.asarray(t) < time)
    after = np.flatnonzero(np.asarray(t) > time)
    if 0 < len(before) <= n_events and len(before) <= len(after):
        return before
    if 0 < len(after) <= n_events:
        return after
    return None


def persistent_drop(hat, r, b, groups, emitter=False, bb=None, br=None, side=None, also=()):
    """The smallest χ² drop (unscaled) of a column b (projected off the model's columns) against residuals r
    (projected too) with the rows of up to PERSIST_EVENTS groups left out: ``groups`` are row indices (into r
    and b) per event in time order (any run of consecutive events: a clock term's evidence is in every row
    after it, not in one or two bad arrivals), or (``emitter``) per array (any of them: the emitter's step is
    one interval's TDOA-S at every array alike, not at one or two; at least two are left). Each by the deletion
    formula: RSS without rows R = RSS − e_R' (I − H_RR)⁻¹ e_R, for the model without b (hat H_RR = ``hat(R)``)
    and with it (H_RR + b_R b_R'/b'b). r and b may hold only some of the rows (the clock's own): ``bb`` = |b|²
    and ``br`` = b'r over every row then. ``side``: the positions (into ``groups``) of a step's events on its
    short side (:func:`end_side`): a run holding all of them is not left out (it would leave the step no
    event on that side: no leave-out can tell those events' arrivals from a clock; :func:`direct_path` does).
    ``also``: more sets of positions (into ``groups``) left out each at once (:func:`penumbra`)."""
    bb = float(b @ b) if bb is None else float(bb)
    if bb <= 0:
        return 0.0
    alpha = (float(b @ r) if br is None else float(br)) / bb
    full, e = alpha * alpha * bb, r - alpha * b
    out = full
    # (the emitter's: at least two arrays left to see it alike)
    for w in range(1, (min(PERSIST_EVENTS, len(groups) - 2) if emitter else PERSIST_EVENTS) + 1):
        runs = (itertools.combinations(groups, w) if emitter else
                (groups[m:m + w] for m in range(len(groups) - w + 1) if side is None or not set(side) <= set(range(m, m + w))))
        for run in runs:
            out = min(out, _drop_without(hat, r, b, e, bb, full, np.unique(np.concatenate(run))))
    for at in also:
        if at and (side is None or not set(side) <= set(at)):
            out = min(out, _drop_without(hat, r, b, e, bb, full, np.unique(np.concatenate([groups[m] for m in at]))))
    return max(float(out), 0.0)


def _drop_without(hat, r, b, e, bb, full, R):
    """:func:`persistent_drop`'s χ² drop ``full`` with the rows R left out (the deletion formula)."""
    I = np.eye(len(R))
    HA = hat(R)
    HB = HA + np.outer(b[R], b[R]) / bb
    dA = r[R] @ np.linalg.lstsq(I - HA, r[R], rcond=1e-10)[0]
    dB = e[R] @ np.linalg.lstsq(I - HB, e[R], rcond=1e-10)[0]
    return full - dA + dB


def penumbra(p, i, doubted):
    """Indices of the events (into ``p.events``) at which array i's arrival, or the reference's that its TDOA-M
    rows hold, is undoubted but next (in time) to one the frontend doubts (``doubted``: :func:`doubted_arrivals`):
    the edge of a run whose line of sight was blocked. There the direct path grazes the obstacle: diffracted and
    weak, a reflection merged with it within the chirp's resolution makes the pick 20-40 µs late, unflagged (rendered
    office dev 501: A4's last arrivals before its reflection-only runs 6-9 and 16-19, events 5 and 15, 38 and 36 µs
    late; dev 503: the reference's events 7 and 17 before its runs 8-9 and 18-19, 23-27 µs late in every array's
    TDOA-M). Two such edges, ten events apart, made a 75 µs and a 30 µs step that no leave-out of PERSIST_EVENTS
    consecutive events removed."""
    bad = _doubted_table(p, doubted)
    order = np.argsort(p.t, kind="stable")
    out = set()
    for a in {i, p.ref}:
        d = bad[a][order]
        edge = ~d & (np.r_[False, d[:-1]] | np.r_[d[1:], False])
        out.update(int(e) for e in order[edge])
    return out


# frontend doubts that an arrival is the direct path's (docs/frontend.md, ``flag``): a direct path weaker than a
# later peak, a reflection only, an array mostly so, too little signal, mics that disagree
ARRIVAL_DOUBTS = ("weak_direct", "nlos", "occluded", "low_snr", "mic_spread")


# ... of which those said of the one arrival ("occluded" is said of every arrival of an array whose direct path is
# weak in 30 % of its events, frontend.extract.OCCLUDED_FRACTION: nothing about this one)
OWN_DOUBTS = tuple(f for f in ARRIVAL_DOUBTS if f != "occluded")


# ... of which no clock can be the cause: a clock shifts every microphone of the array alike and leaves the
# waveform as it is (not so the range track's nlos: a step moves arrivals off their track)
CLOCK_BLIND_DOUBTS = ("weak_direct", "occluded", "low_snr", "mic_spread")


def doubted_arrivals(features, flags=ARRIVAL_DOUBTS):
    """{(array name, event)} whose arrival the frontend doubts as the direct path's (``flags``, by default
    ARRIVAL_DOUBTS, on the array's TDOA-M or DOA row at the event)."""
    out = set()
    for name in ("tdoa_m", "doa"):
        df = features.get(name)
        if df is None or not len(df) or "flag" not in df.columns:
            continue
        bad = has_flag(df, flags)
        out |= set(zip(df["array"].astype(str)[bad], df["event"].to_numpy(int)[bad].tolist()))
    return frozenset(out)


def direct_path(p, fs, i, events, doubted=frozenset()):
    """Whether array i's arrivals at ``events`` (event indices) are the direct path's: none the frontend doubts
    (``doubted``: :func:`doubted_arrivals`), and its DOAs there agree with the fit the factors ``fs`` are
    linearised at (their χ², in the array's own DOA scale, within the χ²₂ₘ quantile at STRUCTURE_ALPHA); False
    where it has no DOA there. A clock step shifts every microphone of the array alike: its intra-array delays,
    the DOA, still point at the source; a reflection's (a blocked line of sight, a chirp detected on an echo)
    point at an image source elsewhere."""
    name = str(p.names[i])
    if any((name, int(p.events[e])) in doubted for e in events):
        return False
    f = next((f for f in fs if f.kind == "doa" and len(f.r) == 3 * len(p.doa.arr)), None)
    if f is None:
        return False
    z2 = np.sum(f.r.reshape(-1, 3) ** 2, axis=1)
    mine = p.doa.arr == i
    at = mine & np.isin(p.doa.ev, events)
    if not at.any():
        return False
    scale2 = max(1.0, float(np.median(z2[mine])) / float(chdtri(2, 0.5)))   # (χ²₂'s median: 2 ln 2)
    return float(np.sum(z2[at])) / scale2 <= float(chdtri(2 * int(at.sum()), STRUCTURE_ALPHA))


def clock_persistence(p, fs, i, comp, groups, hat, r, b, bb=None, br=None, ids=None, doubted=frozenset(),
                      events=None):
    """:func:`persistent_drop` of component ``comp`` of clock i (-1: the emitter, ``groups`` per array; else per
    event, the events' indices ``ids``). A step with at most PERSIST_EVENTS events on one side (:func:`end_side`:
    near a session's start or end) shows in those events' arrivals alone, which no leave-out can tell from
    bad arrivals: the runs holding all of them are not left out, and it persists only where the array's DOAs
    there are the direct path's (:func:`direct_path`, ``doubted``); 0 otherwise. The emitter's drift term
    (``events``: its rows per event) must persist without any one or two consecutive events too, as an array's:
    one array's few bad arrivals in its TDOA-S read as it (rendered lab seed 22: two of A2's readmitted arrivals
    tens of µs off kept an emitter hinge that took another array's warm-up, χ² 26 left without any two arrays);
    its step shows in one interval's rows only, which that would leave out."""
    side = None
    if i >= 0 and comp.kind == "step" and ids is not None:
        side = end_side(p.t[ids], comp.time)
        if side is not None and not direct_path(p, fs, i, ids[side], doubted):
            return 0.0
    # (and without every arrival at the edge of a doubted run at once: :func:`penumbra`)
    edges = penumbra(p, i, doubted) if i >= 0 and ids is not None and doubted else set()
    also = [[m for m, e in enumerate(ids) if int(e) in edges]] if edges else ()
    out = persistent_drop(hat, r, b, groups, i < 0, bb=bb, br=br, side=side, also=also)
    if i < 0 and comp.kind != "step" and events is not None:
        out = min(out, persistent_drop(hat, r, b, events, bb=bb, br=br))
    return out


def _given(pr, rp, O, B, k, j):
    """The χ² drop of candidate k once candidate j is fitted: their columns (B's, on the clock's rows O) and the
    residuals rp projected off the model (``pr``)."""
    def col(m):
        full = np.zeros(len(rp))
        full[O] = B[:, m]
        return pr.resid(full)

    bk, bj, r = col(k), col(j), rp
    a = float(bj @ bj)
    if a <= 0:
        return float((bk @ r) ** 2 / max(float(bk @ bk), 1e-300))
    c = float(bk @ bj)
    den = float(bk @ bk) - c * c / a
    return float((bk @ r - c * float(bj @ r) / a) ** 2 / den) if den > 1e-12 * float(bk @ bk) else 0.0


def _scan_best(p, fs, i, cands, have, basis, sw, scale, tested=None, doubted=frozenset()):
    """The best candidate of each kind of clock i in :func:`joint_scan` (``basis``: the projector, the projected
    residuals rp and the clock's rows, :class:`~calib.estimator.clockscan.ClockRows`; ``sw`` the rows'
    √weights, ``scale`` the TDOA rows' robust scale; ``tested``: the number of candidates the penalty counts,
    those the screen left out too), judged by its persistent χ² (:func:`persistent_drop`) in the clock's own
    robust scale: the best of them as (components, margin, info), or None.

    The persistence tests are gates: of the kinds that pass them, the one with the most evidence on every row
    (the scan's own margin) is the clock's proposal, not the one a leave-out leaves most of — a step's evidence is
    mostly in the TDOA-S of its interval, which its leave-out takes, a smooth term's is spread (bench_clocks
    insert_0.1ms seed 3103: the true step χ² 61.0, 11.0 left; a hinge 34.9, 14.7 left, was taken, and the step
    then fitted only half). Its margin stays the gated one: the clocks' proposals are compared on it (a
    reference's step and the emitter's at one interval, close there, are decided by solving: seed 3208)."""
    from .clockscan import family_columns

    pr, rp, cr = basis
    O = cr.rows
    B = family_columns(cr, cands)
    nb = np.einsum("ij,ij->j", B, B)
    den = nb - pr.explained(O, B)
    ok = den > 1e-12 * np.maximum(nb, 1e-300)
    num = B.T @ rp[O]
    value = np.where(ok, -num / np.where(ok, den, 1.0), 0.0)
    fine = np.array([c.with_value(v).plausible(float(np.ptp(p.t))) for c, v in zip(cands, value)], bool)
    raw = np.where(ok & fine, num * num / np.where(ok, den, 1.0), 0.0)
    if not raw.any() or not len(O):
        return None

    def projected(k):   # the column of candidate k projected off the model, on the clock's rows
        full = np.zeros(len(rp))
        full[O] = B[:, k]
        return pr.resid(full)[O]

    # the array's own scale: its rows' robust spread once its best candidate is fitted (a stated σ below the
    # scatter of this array's arrivals makes no step; neither does a large true step inflate it)
    k0 = int(np.argmax(raw))
    left = (rp[O] + projected(k0) * (value[k0] if ok[k0] else 0.0)) / sw[O]
    scale_i = max(scale, spread(left))
    own = np.zeros(len(rp), bool)
    own[O] = True
    pos = np.full(len(rp), -1)
    pos[O] = np.arange(len(O))
    ids, groups = _event_rows(p, fs, own, ids=True) if i >= 0 else (None, _array_rows(p, fs, own))
    events = [pos[g] for g in groups]
    by_event = [pos[g] for g in _event_rows(p, fs, own)] if i < 0 else None   # (the emitter's drift terms)
    n = len(p.tdoa_s.val) if i < 0 else int(np.sum((p.tdoa_s.arr == i))) + int(np.sum(p.tdoa_m.arr == i))
    best, best_rank, by_kind = None, None, []
    for kind in ("step", "quadratic", "hinge", "warmup"):
        fam = np.flatnonzero([c.kind == kind for c in cands])
        if not fam.size:
            continue
        k = fam[np.argmax(raw[fam])]
        first = float(raw[k]) / scale_i ** 2 - penalty(kind, n, p.N + 1, tested or len(cands))   # (every candidate)
        # persistence: the evidence left with the rows of any PERSIST_EVENTS consecutive events of this array
        # left out (no one or two bad arrivals make a clock term: a step shifts every later row alike)
        # (the emitter's shows in one interval's TDOA-S only, every array's alike: no one or two arrays' rows
        # may carry it); judged only where the scan's own test passes (the margin is the smaller of the two)
        kept_drop = min(float(raw[k]), clock_persistence(p, fs, i, cands[k], events, pr.hat_of(O), rp[O],
                                                         projected(k), bb=den[k], br=-value[k] * den[k], ids=ids,
                                                         doubted=doubted, events=by_event)
                        ) if raw[k] > 0 and first > 0 else None
        # chosen by the scan at its multiplicity; its persistence is one more test of that one candidate
        margin = first if kept_drop is None else min(first, kept_drop / scale_i ** 2 - PERSIST_CHI2)
        if kept_drop is not None and kind == "step" and i >= 0 and end_side(p.t[ids], cands[k].time) is not None:
            margin = min(margin, _end_step_given(cands, raw, k, (pr, rp, O, B)) / scale_i ** 2 - PERSIST_CHI2)
        rank = first if margin > 0 else margin   # (the gates passed: ranked by the evidence on every row)
        by_kind.append((margin, have + [cands[k].with_value(value[k])]))
        if best is None or rank > best_rank:
            new, best_rank = by_kind[-1][1], rank
            # candidates the rows cannot tell apart (an array without rows at the event between two
            # intervals: screened out, or missed) go to the rivals' solves (:func:`_decide`)
            tied = [have + [cands[j].with_value(value[j])] for j in fam
                    if j != k and abs(raw[j] - raw[k]) <= 1e-6 * max(abs(raw[k]), 1.0)]
            best = (new, margin, {"chi2_drop": float(raw[k]) / scale_i ** 2,
                                  "chi2_kept": None if kept_drop is None else kept_drop / scale_i ** 2,
                                  "scale": scale_i, "kind": kind, "test": "joint", "tied": tied, "evidence": rank,
                                  **(_near_intervals(cands, raw, fam, k, scale_i) if margin > 0 else {})})
    if best is not None and best[1] > 0:
        best[2]["kinds"] = _other_kinds(by_kind, best)   # (rivals of another kind)
    return best


def _near_intervals(cands, raw, fam, k, scale):
    """{"near_intervals": {"time": candidate k's, "others": [times]}} for a step candidate ``k`` (``fam``: the
    indices in ``cands`` of its kind's candidates) whose neighbouring step candidates' scan χ² (``raw`` /
    ``scale``²) is within AMBIGUOUS_CHI2 of its, else {} (also for another kind): the rows do not tell in which of
    those intervals the clock stepped (the arrivals of the event between them are all that differ, and its
    source's position absorbs part of them: bench_clocks drop_0.1ms seed 517, the reference's 0.1 ms step
    between events 6 and 7, χ² 31.0 there and 32.8 between 7 and 8, where it was modelled)."""
    if cands[k].kind != "step":
        return {}
    order = fam[np.argsort([cands[j].time for j in fam])]
    pos = int(np.flatnonzero(order == k)[0])
    nb = [order[q] for q in (pos - 1, pos + 1) if 0 <= q < len(order)]
    near = [float(cands[j].time) for j in nb if (raw[k] - raw[j]) / scale ** 2 < AMBIGUOUS_CHI2]
    return {"near_intervals": {"time": float(cands[k].time), "others": near}} if near else {}


def _end_step_given(cands, raw, k, basis):
    """The χ² (unscaled) a step next to the session's start or end (candidate k) keeps once the best smooth
    drift term (a warm-up, the quadratic) is fitted: those few arrivals shifted alike are also the start of a drift
    that varies over the session, which shifts the next events too (not a hinge: one at the first interior event
    IS the first interval's step, the linear clock absorbing the rest); ∞ without one. ``basis``: (projector,
    projected residuals, the clock's rows, the candidates' columns on them), as :func:`_given`."""
    smooth = [j for j in range(len(cands)) if cands[j].kind in ("quadratic", "warmup") and raw[j] > 0]
    if not smooth:
        return np.inf
    return _given(*basis, k, max(smooth, key=lambda j: raw[j]))


# ----------------------------------------------------------------------------------------------- structure
def _split_columns(p, fs, i, comp):
    """Test columns of a component's structure: its column on all but one of the independent row groups that
    see it. An array's clock term: its TDOA-S rows vs its TDOA-M rows, and a step's TDOA-M rows split in two
    at the middle of the events after it (the same size at every later event); the reference's: its TDOA-S
    rows and each other array's TDOA-M rows (every array sees it alike); the emitter's: each array's TDOA-S
    rows. A step of an array's also gets a level change between the two halves of its TDOA-M rows before it."""
    B = _columns(p, fs, i, [comp])[:, 0]
    arr, kind, ev = (np.concatenate(v) for v in zip(*[
        (getattr(p, f.kind).arr if f.kind in ("tdoa_s", "tdoa_m") else np.full(len(f.r), -2),
         np.full(len(f.r), f.kind, dtype=object),
         p.tdoa_m.ev if f.kind == "tdoa_m" else np.full(len(f.r), -1)) for f in fs]))
    S, M = kind == "tdoa_s", kind == "tdoa_m"
    if i < 0:
        groups = [S & (arr == a) for a in range(p.N)]
    elif i == p.ref:
        groups = [S & (arr == i)] + [M & (arr == a) for a in range(p.N) if a != i]
    else:
        groups = [S & (arr == i), M & (arr == i)]
        after = np.unique(ev[M & (arr == i) & (B != 0)])
        if comp.kind == "step" and len(after) >= 2:   # the step's TDOA-M rows: early half vs late half
            late = np.isin(ev, after[len(after) // 2:])
            groups = [groups[0], groups[1] & ~late, groups[1] & late]
    cols = [B * g for g in groups if np.any(B[g] != 0)]
    cols = cols[:-1]
    if comp.kind == "step" and i >= 0 and i != p.ref:
        # and the level before it: the same at every earlier event (a few bad arrivals just before a jump back
        # are no step): the late half of the earlier TDOA-M rows may not differ from the early half
        level = _columns(p, fs, i, [Component("step", -np.inf, 1.0)])[:, 0] * (M & (arr == i))
        before = np.unique(ev[(level != 0) & (B == 0)])
        if len(before) >= 2:
            cols.append(level * np.isin(ev, before[len(before) // 2:]) * (B == 0))
    return np.column_stack(cols) if cols else np.zeros((len(B), 0))


def structure_test(result, models, name, k, features=None):
    """(χ², dof, largest difference of a row group's size from the component's, s) of the hypothesis that
    component k of ``name`` is a clock's, at a ``result`` solved with ``models`` (the features corrected by
    them), or None when it cannot be judged (a problem too large).

    A clock term adds the same h(t) to every arrival the clock stamps: a dropped or inserted block shifts one
    TDOA-S (the interval it falls in) and every later TDOA-M by one size, on all of the array's channels
    alike; the emitter's term shifts every array's TDOA-S alike. Arrivals delayed by reflections (a blocked
    line of sight) vary from event to event and between arrays, so a step fitted to them is two different
    sizes in the TDOA-S and in the TDOA-M (or between arrays). The test: the χ² drop of letting the
    component's part on each row group (:func:`_split_columns`) differ from the rest, after projecting out
    every parameter and component (linearised at the corrected solution, rows Huber-weighted in their robust
    scale, as :func:`joint_scan`); χ² with dof = the number of independent test columns. ``features``: the
    corrected features ``result`` was solved from: every row of the component's clock counts, the ones the solve
    screened out too (a wrong component must not pass by the screening of the rows that contradict it); those
    it left out of the other clocks weigh nothing (:func:`_solved_rows`)."""
    from .problem import make_layout
    from .solver import linearise

    from .clockscan import Projector

    p, st = _every_row(result, features), result["state"]
    lay = make_layout(p)
    if lay.n > SCAN_MAX:
        return None
    lin = linearise(p, st, lay, active_kinds(p), dense=False)
    r = lin.r
    sw, scale = _robust_weights(result, lin, p, own=name)
    index = {**{str(n): j for j, n in enumerate(p.names)}, EMITTER: -1}
    # the rows the solve left out testify about the clock that stamped them only (as in :func:`joint_scan`): an
    # arrival hundreds of σ off (another array's step left unmodelled where its one earlier event was screened
    # as a reflection) reads, through the sources it shares, as this component's misfit (rendered lab seed 28)
    doubted = doubted_arrivals(features) if features is not None else frozenset()
    sizes = [c.value for c in models[name] if c.kind == "step"]
    sw = sw * np.maximum(_solved_rows(result, lin.factors), _witnesses(result, lin, p, index[name], scale, doubted,
                                                                      sizes))
    E, _ = component_columns(p, lin.factors, models)
    T = _split_columns(p, lin.factors, index[name], models[name][k]) * sw[:, None]
    if not T.shape[1]:
        return 0.0, 0, 0.0
    A, prior = _with_nuisance(result, lin, lay, E, sw)
    pr = Projector(A, lay, prior)
    # (Tᵀ P T and Tᵀ P r, not the rows' |P T|²: a nuisance's prior rows hold part of the projections)
    G, g = T.T @ pr.resid(T), T.T @ pr.resid(r * sw)
    lam, W = np.linalg.eigh(0.5 * (G + G.T))
    keep = lam > (1e-6 * max(np.linalg.norm(T), 1e-300)) ** 2
    if not keep.any():
        return 0.0, 0, 0.0
    proj = (W[:, keep].T @ g) / np.sqrt(lam[keep])
    # the groups' sizes less the component's (s): G⁻¹ g in the kept directions
    differ = W[:, keep] @ (proj / np.sqrt(lam[keep]))
    return float(proj @ proj) / scale ** 2, int(keep.sum()), float(np.max(np.abs(differ)))


STRUCTURE_AGREE = 0.01   # a step whose row groups agree on its size to this share of it is a clock's, whatever χ²


def _structure_failures(result, models, old, features):
    """The components new in ``models`` (not in ``old``) that fail :func:`structure_test`, as ban keys
    (name, kind, time). A step whose row groups agree on its size to STRUCTURE_AGREE of it passes even at a
    χ² beyond the test's: a step fitted to reflections takes sizes from delays that change from event to event
    (its groups differ by amounts like its size), while a few reflection-late arrivals beside a true step move
    the groups by a share of their delay, hundreds of row σ where the rows are sub-µs (rendered hall seed 675:
    A2's readmitted 20.000 ms drop, its groups 6 µs apart, χ² 35 on 3 dof from three arrivals 61 µs late)."""
    bad = []
    for name, comps in models.items():
        before = {_key(c) for c in old.get(name, [])}
        for k, c in enumerate(comps):
            if _key(c) in before or c.kind == "arrival":
                continue
            got = structure_test(result, models, name, k, features)
            if (got is not None and got[1] and got[0] > float(chdtri(got[1], STRUCTURE_ALPHA))
                    and not (c.kind == "step" and got[2] <= STRUCTURE_AGREE * abs(c.value))):
                bad.append((name, *_key(c)))
    return bad


# ----------------------------------------------------------------------------------------------- selection
def detect(result, models, banned=frozenset(), excluded=frozenset(), doubted=frozenset(), blind=frozenset(),
           features=None):
    """One detection round at a solved ``result``: proposals {array name: its components with the new one}
    of the arrays whose best new component beats its penalty — the one with the largest margin, and rivals
    within TIE_MARGIN of it (one component per round: a fault bends the fit, and through it the other
    arrays' tests) — and the round's records. The emitter (:data:`EMITTER`, emission times off: the same term in every clock) is
    one more candidate, tested jointly only. ``doubted``: :func:`doubted_arrivals`; ``blind``: those doubted for a
    reason no clock gives (CLOCK_BLIND_DOUBTS), free in the per-array scan (:func:`best_component`). ``features``:
    those ``result`` was solved from; the per-array scan then fits every row of them, the screened ones too
    (:func:`_every_row`): an array's screened rows testify about its own clock, as in its structure test
    (without them a step inside a run of screened events fits every interval of the run alike, and the rivals
    tried were the run's first ones)."""
    p, st = result["problem"], result["state"]
    every = None
    found, records, alternatives = {}, [], {}
    joint = joint_scan(result, models, banned, doubted=doubted)
    suspects = _suspects(result)
    for i in range(-1, p.N):
        name = EMITTER if i < 0 else str(p.names[i])
        if name in excluded:
            continue
        zero = [c.with_value(0.0) for c in models.get(name, [])]
        got = None
        # the fit may be bent around this array: its own robust fits, sources held (not the reference's: a
        # step of its clock shows in every other array's TDOA-M, which its own fit does not see)
        if i >= 0 and i != p.ref and name in suspects:
            if every is None:   # (built once a round, where a per-array scan runs)
                every = p if features is None else _every_row(result, features)
            D = array_data(every, st, i, velocity_arrival_sd(result))
            ref = str(p.names[p.ref])
            skip = {k[1:] for k in banned if k[0] == name} | {("mshift", k[2]) for k in banned if k[:2] == (ref, "step")}
            free = [Component("arrival", float(p.t[k]), 0.0) for k in range(len(p.t))
                    if (name, int(p.events[k])) in blind]
            got = best_component(D, zero, st.x[i].copy(), 1.0 + st.drift[i], st.offset[i], p.N + 1, skip,
                                 reference=name not in _distrusted(result), free=free,
                                 trusted=_trusted(D, every, name, doubted))
        if got is not None and got[0] is not None:
            got[2]["test"] = "array"
        # both tests' best proposals stay: the per-array fit holds the sources at a fit that another array's
        # fault may have bent, so its χ² is not on the joint scan's scale (a reference step read as an
        # outlier-laden array's step); proposals of the two tests are compared by solving (:func:`_decide`)
        for got in (got, joint.get(i)):
            if got is None or got[0] is None:
                continue
            new, margin, info = got
            info = dict(info)
            tied, kinds = info.pop("tied", []), info.pop("kinds", [])
            evidence = info.pop("evidence", margin)
            records.append({"array": name, "margin_chi2": margin, **info})
            if margin > 0:
                for k, alt in enumerate([new] + tied[:MAX_RIVALS - 1]):
                    found[(name, info["test"], k)] = (alt, margin, evidence)
                for k, alt in enumerate(kinds[:MAX_RIVALS - 1]):
                    alternatives.setdefault((name, info["test"]), []).append((alt, margin))
    proposals = []
    for (name, test, _), (new, margin, evidence) in found.items():
        prop = _proposal(p, models, name, new, excluded)
        if prop is not None and not any(prop == q for _, _, _, q in proposals):
            proposals.append((margin, evidence, test, prop))
    if not proposals:
        return [], records, []
    top = _contenders(proposals)
    # and with each clock in it, its other kinds that the evidence does not tell from its best (:func:`_scan_best`)
    for test, prop in list(top):
        for alt, _ in alternatives.get((next(iter(prop)), test), []):
            q = _proposal(p, models, next(iter(prop)), alt, excluded)
            if q is not None and all(q != x for _, x in top):
                top.append((test, q))
    # each clock's best joint proposal, strongest first: partners of a proposal whose structure another clock's
    # unmodelled fault fails (:func:`_paired`)
    partners = []
    for _, _, test, prop in sorted(proposals, key=lambda m: -m[0]):
        if test == "joint" and all(next(iter(prop)) != next(iter(q)) for q in partners):
            partners.append(prop)
    return top, records, partners


def _contenders(proposals):
    """The (test, proposal) pairs of a round to decide by solving (:func:`_decide`), from ``proposals`` (margin,
    evidence, test, proposal), the strongest margin first (a large fault bends the fit and so the others' tests):
    those within TIE_MARGIN (or TIE_SHARE of a large margin) of the best margin, those whose evidence on every row
    (the scan's χ² less its penalty, the persistence gates passed) is as close to the best one's, and the other
    test's best. The gated margins of two clocks are not on one scale: the emitter's step persists without any one
    or two arrays, an array's without one or two consecutive events, which take most of a step's evidence near the
    session's end (bench_clocks two_steps seed 531: the reference's 0.38 ms step three events before the end,
    χ² 97.4, kept 42.3 without two events; the emitter's step at that interval χ² 100.7, kept 72.9 without two
    arrays — taken by its margin, 62 against 32, unsolved; solved, the reference's fits every row better)."""
    proposals = sorted(proposals, key=lambda m: -m[0])
    m0, e0 = proposals[0][0], proposals[0][1]
    tie, tie_e = max(TIE_MARGIN, TIE_SHARE * m0), max(TIE_MARGIN, TIE_SHARE * e0)
    top = [(test, prop) for m, e, test, prop in proposals if m >= m0 - tie or e >= e0 - tie_e][:MAX_RIVALS]
    other = next(((test, prop) for _, _, test, prop in proposals if test != top[0][0]), None)
    if other is not None and other not in top:
        top = top[:MAX_RIVALS - 1] + [other]
    return top


def _proposal(p, models, name, new, excluded):
    """{clock name: its components with the new one, sizes added to the kept ones'} of a scan's proposal
    ``new`` (increments) for clock ``name`` (an "mshift": the reference's step, opposite sign), or None (an
    excluded array, a reference step next to one it has, a pulse: :func:`_pulse`)."""
    if new[-1].kind == "mshift":   # the reference's clock stepped: its step (opposite sign)
        ref = str(p.names[p.ref])
        step = Component("step", new[-1].time, -new[-1].value)
        have = [c.with_value(0.0) for c in models.get(ref, [])]
        allowed = {round(c.time, 9) for c in candidates(p.t, have) if c.kind == "step"}
        if round(step.time, 9) not in allowed:
            return None
        name, new = ref, have + [step]
    if name in excluded:
        return None
    old = models.get(name, [])
    merged = [c.with_value(c.value + (old[k].value if k < len(old) else 0.0)) for k, c in enumerate(new)]
    return None if _pulse(merged) else {name: merged}


PULSE_MATCH = 0.25   # a drop and an insert this close in size (share of the larger) on one array: a pulse


def _pulse(comps):
    """A step that undoes another of the array's (opposite sign, sizes within PULSE_MATCH): the arrivals
    between them are late or early as a block — reflections while the line of sight is blocked, or a bad
    stretch of detections — which no clock does (a buffer that drops samples does not give them back)."""
    steps = [c for c in comps if c.kind == "step"]
    new = steps[-1] if steps and comps[-1].kind == "step" else None
    if new is None:
        return False
    return any(c.value * new.value < 0 and abs(c.value + new.value) <= PULSE_MATCH * max(abs(c.value), abs(new.value))
               for c in steps[:-1])


def _has_pulse(comps):
    """Any two of the array's steps undo each other (:func:`_pulse`)."""
    steps = [c for c in comps if c.kind == "step"]
    return any(_pulse(steps[:k + 1]) for k in range(1, len(steps)))


def _decide(solve, features, models, proposals, options):
    """(models, result, rivals) of the proposal whose solve leaves the smallest robust cost (one solve each:
    Cauchy's ρ over every row, so that a gross outlier no proposal explains weighs nothing; Huber's linear tail
    turned µs-sized moves of another array's rows 20 ms off, an unmodelled step's, into a χ² of 60 between a
    warm-up and a hinge: rendered lab seed 31); rivals: the other proposals the data do not tell from it (their
    χ², twice the robust cost, within AMBIGUOUS_CHI2 of its)."""
    best, costs, sig0 = None, [], None
    for prop in proposals:
        trial = {**models, **prop}
        corrected = correct_features(features, trial)
        res = solve(corrected, **options)
        cost, sig = _robust_cost(res, sig0, corrected, rho=cauchy_rho)
        sig0 = sig if sig0 is None else sig0
        costs.append(cost)
        if best is None or cost < best[0]:
            best = (cost, (trial, res), prop)
    # (the array's scan and the joint scan may propose the same component, sized a little apart: no rival)
    rivals = [prop for prop, c in zip(proposals, costs)
              if _shape(prop) != _shape(best[2]) and 2.0 * (c - best[0]) < AMBIGUOUS_CHI2]
    return (*best[1], rivals)


def _shape(prop):
    """{clock: its components' (kind, time)} of a proposal: what it models, whatever the sizes."""
    return {n: [(c.kind, round(c.time, 9)) for c in comps] for n, comps in prop.items()}


def _last(trial, models):
    """(name, kind, time, value) of the component a trial adds to ``models``."""
    name = next(n for n, c in trial.items() if len(c) > len(models.get(n, [])) or c != models.get(n))
    c = trial[name][-1]
    return name, c.kind, float(c.time), float(c.value)


def _every_row(result, features=None):
    """The problem of a solved ``result``, or (``features`` given: the features it was solved from) that
    problem with every row of those features, the ones the solve screened out too, in its sigmas."""
    from .problem import build_problem

    p = result["problem"]
    if features is not None:
        q = build_problem(features, use_tdoa_s=bool(len(p.tdoa_s.val)), sigma_emit=p.sigma.get("emission", 0.0),
                          odometry_yaw=p.odo_yaw_free)
        if q.K == p.K and q.N == p.N:
            return _motion_corrected(q.replace(sigma={**q.sigma, **p.sigma}, c_free=p.c_free, c_test=p.c_test), p,
                                     result, features)
    return p


MOTION_CORRECTED = (("tdoa_m", "val"), ("tdoa_s", "val"), ("doa", "u"), ("cone", "cos"))   # (kind, measured field)


def _motion_corrected(q, p, result, features):
    """``q`` (the problem of every row of ``features``) with the moving source's correction of the solve
    (``motion.motion_solve``) where it applied one: the solve's own corrected values on the rows it has (``p``),
    the correction at its final state on the rows it screened out. Without it a moving session's tests of
    every row (persistence, structure, robust costs) read the uncorrected arrivals: 100-300σ off, which made
    a true 2 ms step of test_clocks' moving scene unpersistent (χ² 1.8 in a scale of 210)."""
    from .motion import corrected, source_velocities

    if not _motion_record(result).get("applied"):
        return q
    meta = features["meta"]
    vel, _ = source_velocities(features["events"], q.t, q.odom)
    if vel is None:
        return q
    c = corrected(q, result["state"], vel, meta.get("chirp_stretch_shift"), float(meta.get("doa_time_s") or 0.0),
                  meta.get("stretch_time_s"), p.motion.sigma if p.motion is not None else 0.0)
    out = {}
    for kind, field in MOTION_CORRECTED:
        rows, solved = getattr(c, kind), getattr(p, kind)
        pos = _positions(np.asarray(rows.row, int), np.asarray(solved.row, int))
        value = np.array(getattr(rows, field), float)
        value[pos >= 0] = np.asarray(getattr(solved, field))[pos[pos >= 0]]
        out[kind] = dataclasses.replace(rows, **{field: value})
    return c.replace(**out)


def _positions(want, ids):
    """The index in ``ids`` (unique row ids) of each of ``want``, −1 where it is not there (vectorised: every
    row of a large session, each selection round)."""
    if not len(ids):
        return np.full(len(want), -1)
    order = np.argsort(ids)
    k = order[np.minimum(np.searchsorted(ids, want, sorter=order), len(ids) - 1)]
    return np.where(ids[k] == want, k, -1)


def _robust_cost(result, row_sigma=None, features=None, rho=huber_rho):
    """Σ ρ(r) (Huber's by default) over every row (outliers included) at a solved result, whitened by
    ``row_sigma`` (default the result's own: pass the first trial's, so that trials with re-estimated sigmas
    compare in one unit); over every row of ``features`` when given (rows the solve screened out count too: a
    wrong model must not win by screening the rows that contradict it). Returns (cost, the row sigmas used)."""
    from .problem import make_layout
    from .solver import linearise

    p = _every_row(result, features)
    # (rows only: the speed of sound's prior is there when one trial solved c and not when another did not)
    lin = linearise(p, result["state"], make_layout(p), [k for k in active_kinds(p) if k != "speed"])
    own = np.concatenate([np.broadcast_to(f.row_sigma, len(f.r)) for f in lin.factors])
    sig = own if row_sigma is None else row_sigma
    return float(np.sum(rho(lin.r * own / sig))), sig


def _suspects(result):
    """Arrays the fit may be bent around: dropped as inconsistent, or with TDOA rows flagged as outliers."""
    rep = result.get("report") or {}
    out = set(_unreliable(result))
    outliers = result["outliers"] if "outliers" in result else rep.get("outliers") or []
    return out | {o["array"] for o in outliers if o.get("type") in ("tdoa_s", "tdoa_m") and o.get("array")}


def calibrate_clocks(solve, features, *, clock_model="auto", clock_veto=None, readmit=(), **options):
    """``solve(features, **options)`` with per-array clock models chosen by the evidence (module docstring).

    clock_model : "auto" (default): the linear clock unless the evidence asks for steps / drift terms per
        array (0 of 22 clean rendered sessions get a clock term, docs/results.md); "linear":
        never more (``calib.options.OPTIONS``: ``--clock-model``).
    clock_veto : with "auto", a function of no arguments asked once the linear solve is done: a reason (str) to keep
        the linear clock (a clock finding then says so), or None. ``calib estimate`` asks the set-up findings
        it computes meanwhile: a session whose set-up failed as a whole gets no selection, whose trial solves
        only fit clock terms to the mistake (minutes of CPU on another session's odometry).
    readmit : names among ``options["isolate"]`` that the leave-one-array-out test isolated
        (``calibrate``): one whose clock gets components is solved with them and its rows again, and kept in
        where its rows then agree (:func:`_readmit`).
    The result's report (and ``outputs="solution"`` results) get ``clock`` (:func:`clock_report`); the
    arrays' and sources' 1-σ include the components' uncertainty.
    """
    validate_options(clock_model=clock_model)
    result = solve(features, **options)
    linear = result
    # the corrected TDOAs make a new problem (a prebuilt one, ``problem=``, is of the uncorrected features)
    options = {k: v for k, v in options.items() if k != "problem"}
    models, rounds = {}, []
    p = result["problem"]
    # the reference runs at a rate no crystal gives against the emission times: the session's time base
    # (events.csv t_emit, or the reference's stated rate) is wrong; nothing to model (named in the report)
    base_ok = abs(float(result["state"].drift[p.ref])) < RATE_ERROR_MIN
    first = result
    vetoed = clock_veto() if clock_model == "auto" and clock_veto is not None else None
    if clock_model == "auto" and len(p.tdoa_s.val) and base_ok and not vetoed:
        try:
            first, start = _seeded(solve, features, first, options, rounds)
            if start:
                result, models = _auto(solve, features, first, options, rounds, start)
            else:
                result, models, features = _auto_readmitting(solve, features, first, options, rounds)
            result, models = _readmit(solve, features, result, models, options, readmit, first, rounds)
        except ObservabilityError as err:   # a trial model left the data unable to fix something: linear
            result, models = first, {}
            rounds.append([{"rejected": f"a clock model left the problem unobservable ({err}): the linear clock"}])
    _attach_report(result, features, models, rounds, vetoed)
    _speed_at_linear(result, linear, models)
    return result


def _speed_at_linear(result, linear, models):
    """c fixed (report.json ``speed_of_sound.check``): the selection fits clock terms with c as declared, so a
    declared c off the data's can be partly absorbed by a spurious term (an emitter term, a drift term, a µs step:
    rendered lab 501 declared 3 % low read +1.34 % with an emitter term, +3.11 % with the linear clock). Where
    terms were selected and the check at the linear clock reads c significant and further off than the check at
    the final solution, that check is reported (``at_linear_clock``; ``final_relative``, ``final_z``: the
    final solution's). Real clock faults with the right c do not set it off: the linear solve's robust and array
    tests keep the fault's rows out of its check (bench_clocks cases, dev seeds 3500-3503: |z| ≤ 1.1 at the linear
    clock, none significant). In place."""
    final = ((result.get("report") or {}).get("speed_of_sound") or {}).get("check")
    lin = ((linear.get("report") or {}).get("speed_of_sound") or {}).get("check")
    if not models or not final or not lin or linear is result or not lin.get("significant"):
        return
    if abs(lin["relative"]) <= abs(final["relative"]):
        return
    result["report"]["speed_of_sound"]["check"] = {**lin, "at_linear_clock": True,
                                                   "final_relative": final["relative"], "final_z": final["z"]}


def _seeded(solve, features, first, options, rounds):
    """(first, start models): the linear clock's result, or where some array's arrivals jump further than any
    source move allows (:func:`impossible_jumps`: a step so large that the linear solve may find no basin,
    e.g. the reference's) and a step there solves better (a better verdict, or a clearly lower robust cost
    over every row), that solve and those steps (sized by the jump; the selection's joint steps size them)."""
    jumps = impossible_jumps(features)
    if not jumps:
        return first, {}
    events, u = _event_of(features)
    u_of = dict(zip(events.tolist(), u.tolist()))
    start = {}
    for j in jumps:   # (the largest of each array's)
        start.setdefault(j["array"], [Component("step", 0.5 * (u_of[j["after_event"]] + u_of[j["before_event"]]),
                                                j["size"])])
    start = _lost_arrivals(start, jumps, u_of)
    trial = solve(correct_features(features, start), **options)
    # a jump holds the speaker's move between the two events too (0.2 ms at lab seed 21's end, where the rows
    # after it are outliers then, and no later round resizes it): sized again by the level of the array's
    # arrivals after it against those before, at that solve
    sized = _level_sized(trial, correct_features(features, start), start, events, u)
    if sized != start:
        start, trial = sized, solve(correct_features(features, sized), **options)
    # a better verdict (the linear solve found no basin: `failed`), or as good and a robust cost over every row
    # lower by more than one step's χ² at FAMILY_ALPHA
    cost0, sig = _robust_cost(first, None, features)
    cost1, _ = _robust_cost(trial, sig, correct_features(features, start))
    if _rank(trial) > _rank(first) or (_rank(trial) == _rank(first)
                                       and 2.0 * (cost0 - cost1) <= float(chdtri(1, FAMILY_ALPHA))):
        return first, {}
    rounds.append([{"seeded": f"{n}: a step of {c[0].value * 1e3:+.3f} ms at {c[0].time:.3f} s (its arrivals jump "
                              "further than the speaker's move allows)"} for n, c in start.items()])
    return trial, start


def _lost_arrivals(start, jumps, u_of):
    """``start`` ({array: [its one seeded step]}) with, for an array whose largest jump has another next to it
    (sharing an event k) and whose two jumps together still jump (the clock stepped across them), the step sized
    by both and an "arrival" component at k: that one arrival off by what makes the other jump. A chirp that
    falls into a dropped block is stamped with the block's edge: its arrival is off, by less than the block,
    against either side's clock (test_clocks: 50 ms dropped, the chirp 6.2 ms off). Unmodelled, its rows, hundreds
    of σ off, fail the true step's structure test, and through the source they share read as steps of the other
    arrays. Of the two placements (the step in either interval) the one with the smaller arrival error."""
    out = dict(start)
    for name, (c,) in start.items():
        big, *rest = [j for j in jumps if j["array"] == name]
        for j in rest:
            k = {big["after_event"], big["before_event"]} & {j["after_event"], j["before_event"]}
            if len(k) != 1 or abs(big["size"] + j["size"]) <= max(big["allowed"], j["allowed"]):
                continue   # (not adjacent; or a pure outlier, one arrival off and back: no step, screened)
            k = k.pop()
            # the step stays in the larger jump's interval; the arrival at k explains the smaller one, whose sign
            # is the arrival's when the arrival opens it (k its earlier event), the opposite when it closes it
            out[name] = [c.with_value(big["size"] + j["size"]),
                         Component("arrival", u_of[k], j["size"] if j["before_event"] == k else -j["size"])]
            break
    return out


def _beside_steps(models, t):
    """``models`` less each "arrival" component (:func:`_lost_arrivals`) without a step of its array in an
    interval its event ends (event times ``t``), and less the arrays left without components. A chirp lost in a
    dropped block is at that block's edge: without the step it is one outlier, which the robust solve screens;
    an arrival term alone takes that array's rows at the event out of the fit unjudged (no test weighs it:
    featsim seed 6 of test_motion_noise, a source mis-placed at one event, left A5 an arrival 1.2 ms off and no
    step, 10 cm off)."""
    t = np.unique(np.asarray(t, float))

    def ends(c):   # (the events that end the step's interval)
        k = int(np.searchsorted(t, c.time)) - 1
        return {t[j] for j in (k, k + 1) if 0 <= j < len(t)}

    out = {}
    for name, comps in models.items():
        edges = set().union(*[ends(c) for c in comps if c.kind == "step"])
        kept = [c for c in comps if c.kind != "arrival" or any(abs(c.time - e) <= 1e-9 * max(1.0, abs(e))
                                                                for e in edges)]
        if kept:
            out[name] = kept
    return out


def _level_sized(result, corrected, start, events, u):
    """``start`` ({array: [its one step]}) with each step's size corrected by the level of the array's TDOA-M
    after it against before it at ``result`` (solved from ``corrected``, the features less ``start``:
    :func:`_block_lag`, every row); ``events``, ``u``: the events and their times (:func:`_event_of`)."""
    out = {}
    for name, comps in start.items():
        c = comps[0]
        got = _block_lag(result, corrected, name, [int(e) for e in np.asarray(events)[np.asarray(u) > c.time]],
                         c.time, 1)
        out[name] = [c.with_value(c.value - got[0]) if got is not None and np.isfinite(got[0]) else c] + list(comps[1:])
    return out


READMIT_SPREAD = 0.02   # a doubted block's lags vary by less than this share of their size: one constant lag
READMIT_SIGMAS = 20.0   # ... and that lag is this many times their spread (and the rows' σ) at least


def _doubted_blocks(features):
    """[(array, block events, (event before, event after) the boundary, the events beyond it)]: each array whose own arrivals the
    frontend doubts as reflections (flag ``nlos``, :func:`calib.estimator.screen.own_doubted_events`) at a
    run of its consecutive events that starts or ends its session (but for at most PERSIST_EVENTS events
    before or after it, which a clock step shifts alike: :func:`end_side`), with at least PERSIST_EVENTS events
    in it and MIN_EVENTS outside every doubted one; or the session's first or last event alone (a step next to
    it, rendered lab seed 28, A2's event 0 of 0-13, 19.8 ms late against its range track, or a reflection:
    :func:`_readmitted` does not readmit it and says so, :func:`_one_arrival`). Other doubted events of the
    array (true reflections elsewhere: rendered hall seed 675, A2's 20 ms drop after events 0-3, events 5 and
    11 doubted too) do not hide the run; they stay doubted. The events beyond it: the array's on the block's
    side of the boundary, outside it (those a step there shifts as it, :func:`_readmitted`)."""
    from .screen import DROP_FLAGS, own_doubted_events

    names = [n for n in DROP_FLAGS["nlos"] if len(features[n])]
    doubt = {n: has_flag(features[n], ("nlos",)) for n in names}
    if not any(d.any() for d in doubt.values()):
        return []
    out = []
    flagged = {str(a) for n in names for a in features[n]["array"][doubt[n]]}
    for a in (str(n) for n in features["meta"]["arrays"] if str(n) in flagged):
        bad = own_doubted_events(features, doubt, a)
        evs = sorted({int(e) for n in names if "event" in features[n]
                      for e in features[n]["event"][features[n]["array"].astype(str) == a]})
        pos = np.flatnonzero(np.isin(evs, sorted(bad)))
        if len(evs) - len(pos) < MIN_EVENTS:
            continue
        for run in np.split(pos, np.flatnonzero(np.diff(pos) != 1) + 1) if len(pos) else ():
            edge = len(run) == 1 and run[0] in (0, len(evs) - 1)
            if len(run) < PERSIST_EVENTS and not edge:
                continue
            if run[0] <= PERSIST_EVENTS and run[-1] < len(evs) - 1:
                out.append((a, [evs[k] for k in run], (evs[run[-1]], evs[run[-1] + 1]), evs[:run[0]]))
            elif run[-1] >= len(evs) - 1 - PERSIST_EVENTS and run[0] > 0:
                out.append((a, [evs[k] for k in run], (evs[run[0] - 1], evs[run[0]]), evs[run[-1] + 1:]))
    return out


def _without_nlos(features, array, block, reference):
    """A copy of ``features`` with the flag ``nlos`` taken off ``array``'s rows at the events ``block`` (every
    array's TDOA-M there for the reference: its arrival is in each)."""
    out = dict(features)
    for name in ("tdoa_m", "tdoa_s", "doa"):
        df = features[name]
        if "flag" not in df.columns or not len(df):
            continue
        if "event" in df.columns:
            at = df["event"].isin(block).to_numpy()
        else:
            at = (df["from_event"].isin(block) | df["to_event"].isin(block)).to_numpy()
        mine = at & ((df["array"].astype(str) == array).to_numpy() | (reference and name == "tdoa_m"))
        if not mine.any():
            continue
        flag = flag_text(df)
        cleared = flag.str.split("+").map(lambda parts: "+".join(x for x in parts if x and x != "nlos"))
        df = df.copy()
        df["flag"] = np.where(mine, cleared, flag)
        out[name] = df
    return out


def _event_positions(p, events):
    """Positions (into ``p.events``) of the event ids ``events`` the problem has, in their order."""
    index = {int(e): k for k, e in enumerate(p.events)}
    return [index[int(e)] for e in events if int(e) in index]


def _block_lag(first, features, array, block, time, min_rows=PERSIST_EVENTS, beyond=()):
    """(lag, spread, σ, agreeing events, events off) of ``array``'s TDOA-M at the events ``block`` (on one side of ``time``, s since t0)
    against its other events', at the first solve's sources: model − data (s) over the block less that over the
    rest, the block's robust spread, the rows' σ. An array's own: its robust fit (:func:`fit_array`: position,
    clock and a step at ``time``, sources held), the step's size (its sign as a lag) and the spread of the
    block's residuals at that fit. Not against the first solve's pose: an array whose doubted events are most of
    its own is refitted alone to every row, neither side, and then neither lags by the step (rendered lab seed
    27, events 0-7 of 0-13: 0 against the fit; bench_clocks, 20 of 36 events before a 5.9 ms drop: 1.9 ± 0.7
    ms). The reference's: the medians over every array's TDOA-M (the first solve's sources are every array's).
    The agreeing events: the block's whose lag is the block's (:func:`_agreeing`;
    a reflection-only arrival beside a step lags by its excess path too: rendered lshape, an array's occluded
    first event 19 ms late beside two 5 ms late of a drop, readmitted with them, failed the step's structure).
    The events off: those of ``beyond`` (events on the block's side of ``time``, outside it) with rows, whose
    level is not the block's by the same tolerance (:func:`_agreeing`)."""
    from .problem import make_layout
    from .solver import linearise

    p = _every_row(first, features)
    if "tdoa_m" not in active_kinds(p):
        return None
    i = [str(n) for n in p.names].index(array)
    at, out = _event_positions(p, block), _event_positions(p, beyond)
    mine = (p.tdoa_m.arr == i) | (i == p.ref)
    rows = mine & np.isin(p.tdoa_m.ev, at)
    if rows.sum() < min_rows or not (mine & ~rows).any():
        return None
    sign = 1.0 if np.all(p.t[at] < time) else -1.0   # (model − data on the block = the step's size before it)
    if i != p.ref:
        st = first["state"]
        D = array_data(p, st, i)
        # (its pose held by the rows the frontend does not doubt, the block's and the rest: :func:`fit_array`)
        _, _, _, coef, r = fit_array(D, [Component("step", time, 0.0)], st.x[i].copy(), 1.0 + st.drift[i],
                                     st.offset[i], _trusted(D, p, array, doubted_arrivals(features)))
        on, off = np.isin(D.j, at), np.isin(D.j, out)
        e = r[len(D.zs):] * np.broadcast_to(D.sig_m, len(D.ym))
        sigma = float(np.median(np.broadcast_to(D.sig_m, len(D.ym))))
        center, spread = float(np.median(e[on])), float(mad_std(e[on]))
        return (sign * float(coef[0]), spread, sigma,
                _agreeing(p.events[D.j[on]], e[on], center, float(coef[0]), max(spread, sigma)),
                _disagreeing(p.events[D.j[off]], e[off], center, float(coef[0]), max(spread, sigma)))
    f = linearise(p, first["state"], make_layout(p), ["tdoa_m"]).factors[0]
    e = -f.r * np.broadcast_to(f.row_sigma, len(f.r))
    lag = float(np.median(e[rows]))
    spread, sigma = float(mad_std(e[rows], center=lag)), float(np.median(np.broadcast_to(f.row_sigma, len(f.r))))
    size = lag - float(np.median(e[mine & ~rows]))
    off = mine & np.isin(p.tdoa_m.ev, out)
    return (size, spread, sigma, _agreeing(p.events[p.tdoa_m.ev[rows]], e[rows], lag, size, max(spread, sigma)),
            _disagreeing(p.events[p.tdoa_m.ev[off]], e[off], lag, size, max(spread, sigma)))


def _agreeing(events, e, center, lag, spread):
    """The events (sorted) whose rows' median ``e`` is the block's ``center`` within what its readmission allows
    of a ``lag``'s spread (READMIT_SPREAD of it) or HUBER_K of the block's ``spread``, whichever is larger."""
    ev = np.asarray(events, int)
    tol = max(READMIT_SPREAD * abs(lag), HUBER_K * spread)
    return [int(k) for k in np.unique(ev) if abs(float(np.median(e[ev == k])) - center) <= tol]


def _disagreeing(events, e, center, lag, spread):
    """The events (sorted) with rows that :func:`_agreeing` does not count as the block's."""
    ev = np.asarray(events, int)
    return sorted(set(np.unique(ev).tolist()) - set(_agreeing(ev, e, center, lag, spread)))


def _block_direct(first, features, array, block):
    """Whether ``array``'s bearings at the events ``block`` (two or more) are the direct path's at the solve
    ``first`` (its features: ``features``, every row): at a solve that fitted them (a left-out row's residual is a
    prediction's, wider than its σ): :func:`_bearings_direct` (its DOA rows, or a linear array's or pair's cone
    rows: its bearing a cone about its axis)."""
    from .problem import make_layout
    from .solver import linearise

    p = _every_row(first, features)
    names = [str(n) for n in p.names]
    kinds = [k for k in ("doa", "cone") if k in active_kinds(p)]
    if array not in names or not kinds:
        return False
    i = names.index(array)
    fs = linearise(p, first["state"], make_layout(p), kinds).factors
    at = _event_positions(p, block)
    return len(at) >= PERSIST_EVENTS and _bearings_direct(p, fs, i, at)


def _bearings_direct(p, fs, i, events):
    """Whether array i's bearings at ``events`` (a block of them) are mostly the direct path's: the MEDIAN over
    them of its bearing's χ² (DOA: 2 dof; a linear array's or pair's cone row: 1), in the array's own scale,
    within the χ² quantile at STRUCTURE_ALPHA. A blocked line of sight sends every arrival of the run by the
    reflector, far off; a step's DOAs sit among the array's others. The median, not :func:`direct_path`'s sum
    and its veto of any doubted arrival: a sum over many events at a trial fit that something unmodelled bends
    (another array's warm-up) rejects a step whose DOAs sit 1.4× their σ (bench_clocks drop_doubted_and_warmup
    seed 3501: 18 events, χ² 74 > 68), and rendered rooms doubt some of a step's arrivals (weak_direct, and then
    ``occluded`` on every arrival of the array: rendered deploy dev 543, A2's 20 ms drop, events 0-7)."""
    kind, rows = ("doa", p.doa) if np.any(p.doa.arr == i) else ("cone", p.cone)
    dim = 3 if kind == "doa" else 1
    f = next((f for f in fs if f.kind == kind and len(f.r) == dim * len(rows.arr)), None)
    if f is None:
        return False
    z2 = np.sum(f.r.reshape(-1, dim) ** 2, axis=1)
    dof = 2 if kind == "doa" else 1
    mine = rows.arr == i
    at = mine & np.isin(rows.ev, events)
    if not at.any():
        return False
    scale2 = max(1.0, float(np.median(z2[mine])) / float(chdtri(dof, 0.5)))
    return float(np.median(z2[at])) / scale2 <= float(chdtri(dof, STRUCTURE_ALPHA))


def _one_arrival(rounds, array, event, before, after, lag):
    """Say (in ``rounds``, once) that ``array``'s doubted arrival at the session's first or last ``event``, off
    by ``lag`` (s) against its other events, stays out: one arrival cannot tell a clock step
    between ``before`` and ``after`` from a reflection-only arrival. Both shift every row of that one arrival
    (its TDOA-M with each array, its TDOA-S, its range track) by one amount, and a step there changes nothing
    else in the solution; its DOA is no proof (a reflection's bearing can lie near the source's, within a wide
    DOA σ: fault-free dev renders deploy 515 A1 and ushape 501 A3, event 0 15.7 and 16.1 ms late, passed
    :func:`direct_path`, and the warehouse check session's false 23.5 ms step was one such at its last event),
    and reflection-only arrivals at a session's ends (36 over 123 fault-free dev renders) are far likelier than
    a fault in its first or last interval."""
    note = (f"{array}: event {event} alone, doubted as a reflection, is {abs(lag) * 1e3:.3f} ms off its other "
            f"events: a clock step between events {before} and {after} would look the same in every row of one "
            "arrival; not modelled, its rows stay out (doubted)")
    if not any(r.get("rejected") == note for rnd in rounds for r in rnd):
        rounds.append([{"rejected": note}])


def _readmitted(solve, features, first, options, rounds, models=None):
    """(first, start models, features): where the frontend doubts an array's arrivals as reflections over a
    block of events (two or more: one alone, :func:`_one_arrival`) that opens or closes its session
    (:func:`_doubted_blocks`) and those arrivals are late (or
    early) by ONE constant amount against the first solve (:func:`_block_lag`: a reflection's excess path
    changes as the robot moves, a dropped or inserted sample block's does not), the rows are readmitted with a
    step at the block's edge; kept when that solves better (as :func:`_seeded`), the step persists (the array's
    undoubted events beyond the block on its side lag with it: reflections end where the line of sight returns)
    and the block's DOAs are the direct path's (:func:`_block_direct`: a robot standing still behind an obstacle
    gets one reflection, late by one amount, at each chirp). Else (first, ``models``, features). ``models``: the clock models ``first`` was solved with (kept, the step added to them)."""
    models = dict(models or {})
    events, u = _event_of(features)
    u_of = dict(zip(events.tolist(), u.tolist()))
    ref = str(features["meta"]["reference_array"])
    doubted = doubted_arrivals(features, OWN_DOUBTS)   # (a doubted arrival beyond a block: no evidence either way)
    for array, block, (before, after), beyond in _doubted_blocks(features):
        time = 0.5 * (u_of[before] + u_of[after])
        if any(c.kind == "step" and abs(c.time - time) < 1e-9 for c in models.get(array, [])):
            continue
        readmitted = _without_nlos(features, array, block, array == ref)
        got = _block_lag(first, correct_features(readmitted, models), array, block, time, len(block),
                         [k for k in beyond if (array, int(k)) not in doubted])
        if got is None:
            continue
        lag, spread, sigma, agree, off = got
        if not (spread <= READMIT_SPREAD * abs(lag) and abs(lag) >= READMIT_SIGMAS * max(spread, sigma)):
            continue
        if len(block) < PERSIST_EVENTS:   # one arrival: a step beside it or a reflection, alike (:func:`_one_arrival`)
            _one_arrival(rounds, array, block[0], before, after, lag)
            continue
        if off:   # the direct path's arrivals beyond it are not shifted with it: the run of reflections ended
            continue
        if agree != list(block):   # (the rest lag by more: reflections on top of the step, still doubted)
            if (before if block[-1] == before else after) not in agree:
                continue
            block = agree
            readmitted = _without_nlos(features, array, block, array == ref)
        # model − data = c on the block's rows when it precedes the step (the fit follows the later clock)
        size = lag if block[-1] == before else -lag
        start = {**models, array: models.get(array, []) + [Component("step", time, size)]}
        corrected = correct_features(readmitted, start)
        trial = solve(corrected, **options)
        cost0, sig = _robust_cost(first, None, correct_features(readmitted, models))
        cost1, _ = _robust_cost(trial, sig, corrected)
        if _rank(trial) > _rank(first) or 2.0 * (cost0 - cost1) <= float(chdtri(1, FAMILY_ALPHA)):
            continue   # (a worse verdict, or no better fit: STATUS_RANK grows from ok)
        if not _block_direct(trial, corrected, array, block):
            continue   # a constant lag is a step's or a paused robot's reflections alike in the TDOAs; the DOAs tell
        rounds.append([{"readmitted": f"{array}: events {block[0]}-{block[-1]}, doubted as reflections, are "
                                      f"{abs(lag) * 1e3:.3f} ms {'late' if lag < 0 else 'early'} alike (spread "
                                      f"{spread * 1e6:.1f} µs): a clock step between events {before} and {after}, "
                                      "not reflections; readmitted"}])
        return trial, start, readmitted
    return first, models, features


def _auto_readmitting(solve, features, first, options, rounds):
    """:func:`_auto` from the linear clock's ``first`` with the doubted blocks readmitted (:func:`_readmitted`):
    (result, models, the features they are of). A readmitted block's rows stand only with their step: where the
    selection removes it, the block stays out (rendered lab seed 35: the step, failing its structure test at a fit
    an unmodelled warm-up bent, was removed and left seven events 20 ms off undoubted: 427 cm). Where nothing was
    readmitted at the linear fit, the blocks are measured again at the fit with the models the selection chose
    (rendered lab seed 25: A3's warm-up had bent the first fit, the trial named A3)."""
    def holds(models, start, base):   # (the readmitted steps are still modelled)
        return all(_key(c) in {_key(m) for m in models.get(n, [])} for n, comps in start.items()
                   for c in comps if _key(c) not in {_key(m) for m in base.get(n, [])})

    trial, start, readmitted = _readmitted(solve, features, first, options, rounds)
    if start:
        result, models = _auto(solve, readmitted, trial, options, rounds, start)
        if holds(models, start, {}):
            return result, models, readmitted
        rounds.append([{"rejected": "the readmitted block's step was not kept: its rows stay out (doubted)"}])
    result, models = _auto(solve, features, first, options, rounds)
    if models:
        again, more, readmitted = _readmitted(solve, features, result, options, rounds, models)
        if more != models:
            res, got = _auto(solve, readmitted, again, options, rounds, more)
            if holds(got, more, models):
                return res, got, readmitted
            rounds.append([{"rejected": "the readmitted block's step was not kept: its rows stay out (doubted)"}])
    return result, models, features


def _auto(solve, features, first, options, rounds, start=None):
    """The selection of :func:`calibrate_clocks` from the linear clock's ``first`` result (solved with the
    ``start`` models, :func:`_seeded`): (result, models)."""
    excluded = set()
    for _ in range(2):   # (a second selection without the arrays the first one could not explain)
        models, result = _select(solve, features, first, options, rounds, excluded, start)
        if not models:
            result = first
            break
        result, models, bad, removed = _refine_and_resolve(solve, features, result, models, options, first)
        if removed and not bad:
            # a component the joint judgement removed leaves what it fitted unexplained (a warm-up taken for a
            # step next to the session's start, which the leave-out then rejects): the selection looks again
            # from what is kept, without the removed ones
            more, res = _select(solve, features, result, options, rounds, excluded, models, removed)
            if more != models:
                result, models, bad, _ = _refine_and_resolve(solve, features, res, more, options, first)
        if not bad:
            break
        excluded |= set(bad)
        rounds.append([{"rejected": f"{n}: its clock terms did not explain its rows (still named as inconsistent); "
                                    "selected again without it"} for n in sorted(bad)])
    if models and _worse(result, first):   # the models did not explain the data: the linear clock's result
        result, models = first, {}
        rounds.append([{"rejected": "the clock models left the fit worse than the linear clock's"}])
    return result, models


def _select(solve, features, result, options, rounds, excluded=frozenset(), start=None, banned=()):
    """Detection rounds from the linear clock's ``result``: each adds the best proposal (:func:`detect`,
    rivals decided by :func:`_decide`) and solves again; a new component of the joint scan that fails its
    structure test (:func:`structure_test`) is taken out again and not proposed again. The arrays in ``excluded`` get no
    components (nor their steps seen as the reference's). ``start``: the models ``result`` was solved with;
    ``banned``: (name, kind, time) keys not to propose. Returns (models, result)."""
    models, banned, aside, kept, rejected = dict(start or {}), set(banned), set(), 0, 0
    while kept < MAX_ROUNDS and rejected < MAX_REJECTED:
        proposals, records, partners = detect(result, models, frozenset(banned | aside), frozenset(excluded),
                                              doubted_arrivals(features), doubted_arrivals(features, CLOCK_BLIND_DOUBTS),
                                              correct_features(features, models))
        rounds.append(records)
        if not proposals:
            break
        if len(proposals) == 1:
            (test, prop), = proposals
            trial = {**models, **prop}
            res = solve(correct_features(features, trial), **options)
        else:
            trial, res, rivals = _decide(solve, features, models, [prop for _, prop in proposals], options)
            test = next(t for t, prop in proposals if {**models, **prop} == trial)
            if rivals:
                rounds.append([{"ambiguous": [_last(trial, models)] + [_last({**models, **r}, models) for r in rivals]}])
        # proposals of the joint scan come from a fit not bent around them: their structure is judged at once;
        # a per-array scan's (a fault large enough to bend the fit) may be placed or sized provisionally until
        # the fault is modelled in full: judged at the end (:func:`_refine_and_resolve`)
        if test == "joint":
            trial, res = _resize(solve, features, trial, res, options)
            bad = _structure_failures(res, trial, models, correct_features(features, trial))
            names = {b[0] for b in bad}
            pending = any(r.get("margin_chi2", 0.0) > 0 and r.get("array") not in names for r in records)
            paired = _paired(solve, features, models, trial, names, partners, options) if bad and pending else None
            if paired is not None:   # the two faults together: each one's structure holds once the other is modelled
                trial, res = paired
                rounds.append([{"paired": [_last({n: c}, models) for n, c in trial.items() if c != models.get(n)]}])
            elif bad:
                rejected += 1
                # another clock's fault still unmodelled shows in this one's row groups (a reference step's
                # test reads every array's TDOA-M): set aside until a component is taken, banned otherwise
                (aside if pending else banned).update(bad)
                rounds.append([{"rejected": f"{b[0]}: {b[1]} at {b[2]:.3f} s: not a clock's structure (TDOA-S and "
                                            "TDOA-M, or the arrays, disagree on its size)"
                                            + (" while another clock's fault is unmodelled: set aside" if pending else "")}
                               for b in bad])
                continue
        elif _end_step_unpersistent(res, trial, models, features):
            # a per-array proposal is judged at the end, but a step next to the session's start or end rests on
            # those few arrivals alone, which no other fault bends: judged at once (a warm-up's first arrivals
            # read as a step would leave the warm-up itself unmodelled)
            name, kind, time, _ = _last(trial, models)
            rejected += 1
            pending = any(r.get("margin_chi2", 0.0) > 0 and r.get("array") != name for r in records)
            (aside if pending else banned).add((name, kind, round(time, 9)))
            rounds.append([{"rejected": f"{name}: {kind} at {time:.3f} s next to the session's end: not persistent "
                                        "(its few arrivals there are not shifted alike, or not on the direct path)"}])
            continue
        models, result, kept = trial, res, kept + 1
        aside.clear()
    return models, result


def _paired(solve, features, models, trial, failed, partners, options):
    """(models, result) of ``trial`` (a joint proposal whose components on the clocks ``failed`` fail their structure
    test while another clock's fault is unmodelled) with the best joint proposal of another clock (``partners``,
    from :func:`detect`), solved and resized together, where no new component of the pair fails its structure
    test; the first such of at most MAX_RIVALS partners, or None. Two large faults at once bend the fit around
    each other: a 6.1 ms reference step, taken alone, failed its structure test at χ² 3412 on 4 dof while another
    array's 2.6 ms step was unmodelled, and one at a time the selection then took the reference's step an
    interval off, sized by that array's rows (bench_clocks two_steps, seed 509)."""
    tried = 0
    for prop in partners:
        name = next(iter(prop))
        if name in failed or trial.get(name) != models.get(name):   # (a partner on another clock only)
            continue
        pair = {**trial, **prop}
        res = solve(correct_features(features, pair), **options)
        pair, res = _resize(solve, features, pair, res, options)
        if not _structure_failures(res, pair, models, correct_features(features, pair)):
            return pair, res
        tried += 1
        if tried >= MAX_RIVALS:
            break
    return None


def _end_step_unpersistent(res, trial, models, features):
    """Whether the component ``trial`` adds to ``models`` is a step within PERSIST_EVENTS events of the session's
    start or end (:func:`end_side`) that fails its persistence at ``res`` (:func:`persistence`)."""
    name, kind, time, _ = _last(trial, models)
    if kind != "step" or name == EMITTER or end_side(res["problem"].t, time) is None:
        return False
    chi2 = persistence(res, trial, correct_features(features, trial)).get((name, len(trial[name]) - 1))
    return chi2 is not None and chi2 < PERSIST_CHI2


RESIZE_SIGMA = 1.0   # a joint step moving a new component by more than this × its σ: solved again before judging it
RESIZE_ROUNDS = 3


def _resize(solve, features, trial, res, options):
    """The scan's size of a component is linear at a fit its fault bent: a 6.8 ms reference step came out
    7.2 ms, and the 40σ left failed its structure test. Joint Gauss–Newton steps (:func:`refine`) and solves
    until it moves by less than RESIZE_SIGMA σ. Returns (models, result)."""
    for _ in range(RESIZE_ROUNDS):
        moved, new, _ = refine(res, trial)
        shift = max((abs(c.value - o.value) / max(c.std or 0.0, 1e-300) for n in new for c, o in zip(new[n], trial[n])),
                    default=0.0)
        if not moved or shift <= RESIZE_SIGMA:
            break
        trial = {n: [c.with_value(c.value) for c in comps] for n, comps in new.items()}
        res = solve(correct_features(features, trial), **options)
    return trial, res


def _rank(result):
    from .verdict import STATUS_RANK

    return STATUS_RANK.get(((result.get("report") or {}).get("verdict") or {}).get("status"), 0)


def _worse(result, first):
    """The result with clock models is worse than the linear clock's: a worse verdict, or (solution outputs)
    not converged where that one was, or more unreliable arrays."""
    from .verdict import STATUS_RANK

    rank = [STATUS_RANK.get(((r.get("report") or {}).get("verdict") or {}).get("status"), 0) for r in (result, first)]
    conv = [bool(r["report"]["converged"] if "report" in r else r.get("converged", True)) for r in (result, first)]
    return rank[0] > rank[1] or (conv[1] and not conv[0]) or len(_unreliable(result)) > len(_unreliable(first))


def _refine_and_resolve(solve, features, result, models, options, first=None):
    """The joint step for the components (:func:`refine`), then backward elimination: the component whose
    joint χ² (value / σ)² falls furthest short of its penalty is removed and the session solved again (a
    component taken while a larger fault still bent the fit may not be needed once that fault is modelled);
    solved again too when the joint step moved a component by more than REFIT_SIGMA of its σ. Returns
    (result, models, the arrays whose components were all removed at the end: still named). A component
    that fails its structure test (:func:`structure_test`) at the solution with all of them is removed too
    (each was tested when taken, with the components then held; those may have gone since). ``first``: the
    linear clock's result (:func:`_doa_worse`). Also returns the (name, kind, time) keys of the components
    removed as weak, unstructured or unpersistent."""
    cov_info, removed = None, []
    for _ in range(2 * sum(len(c) for c in models.values()) + 2):
        moved, models, cov_info = refine(result, models)
        weak = (_weakest(result["problem"], models) or _unstructured(result, features, models)
                or _unpersistent(result, features, models))
        if weak is not None:
            name, k = weak
            removed.append((name, *_key(models[name][k])))
            models = _beside_steps({**models, name: [c for j, c in enumerate(models[name]) if j != k]},
                                   result["problem"].t)
        elif not moved:
            break
        result = solve(correct_features(features, models), **options)
        if not models:
            return result, models, [], removed
    # an array the session still contradicts with its components (dropped as inconsistent, or named for
    # holding the outliers: biased as a whole): they did not explain it, a reflection's bias is no clock's; it
    # keeps the linear clock and the consistency tests name it as before
    # (an array isolated by request is unreliable by construction: that says nothing of its terms)
    flagged = ((result.get("report") or {}).get("verdict") or {}).get("flagged_arrays") or []
    isolated = set(options.get("isolate") or ())
    bad = [n for n in (set(_unreliable(result)) - isolated) | set(flagged) if n in models]
    bad += [n for n, comps in models.items() if n not in bad and _has_pulse(comps)]
    # a clock term moves no DOA: an array whose DOAs fit worse with its terms (its pose moved to where the terms
    # and the TDOAs agree: reflections, not a clock) keeps the linear clock
    bad += [n for n in _doa_worse(first, result, features, models) if n not in bad]
    if bad:
        models = {n: c for n, c in models.items() if n not in bad}
        result = solve(correct_features(features, models), **options)
        cov_info = refine(result, models)[2] if models else None
    _apply_std(result, cov_info)
    return result, models, bad, removed


def _readmit(solve, features, result, models, options, names, first, rounds):
    """(result, models): ``result`` solved again with the arrays ``names`` (isolated by the leave-one-array-out
    test) that got clock components back in, where the joint judgement (:func:`_refine_and_resolve`) then keeps
    every one of their components and names none of them (unreliable, flagged, DOAs worse). An array whose
    unmodelled step bent the first fit is found inconsistent with the others; only once its rows are out does
    its step show in the scan (the sources no longer bent around it), and isolated it is then refitted alone:
    bench_clocks seed 529, A5's 0.91 ms drop found at margin 492 χ², and A5 lost (refitted alone, unreliable)."""
    back = [n for n in names if models.get(n)]
    if not back:
        return result, models
    opts = {**options, "isolate": [n for n in options.get("isolate") or () if n not in back]}
    try:
        trial = solve(correct_features(features, models), **opts)
        trial, got, bad, removed = _refine_and_resolve(solve, features, trial, models, opts, first)
        lost = set(bad) | {r[0] for r in removed} | set(_unreliable(trial))
    except ObservabilityError:
        lost = set(back)
    if lost & set(back) or _worse(trial, result):
        rounds.append([{"rejected": f"{n}: not readmitted (its rows with its clock terms still disagree with the "
                                    "others'): solved without them"} for n in back])
        return result, models
    rounds.append([{"readmitted": f"{n}: its clock terms explain its rows: solved with them"} for n in back])
    return trial, got


def _doa_cost(result, features, sigma=None, doubted=frozenset()):
    """(per array: 2 Σ Huber of its DOA and cone residuals, every row of ``features`` but those of the arrivals in
    ``doubted``, whitened by ``sigma`` (default the result's own row σ), those row σ)."""
    from .problem import make_layout
    from .solver import linearise

    p = _every_row(result, features)
    kinds = [k for k in active_kinds(p) if k in ("doa", "cone")]
    if not kinds:
        return np.zeros(p.N), {}
    lin = linearise(p, result["state"], make_layout(p), kinds)
    arr = row_arrays(p, lin.factors)
    phys = np.concatenate([f.r * np.broadcast_to(f.row_sigma, len(f.r)) for f in lin.factors])
    own = np.concatenate([np.broadcast_to(f.row_sigma, len(f.r)) for f in lin.factors])
    sig = own if sigma is None or len(sigma) != len(own) else sigma
    bad = _doubted_table(p, doubted)
    out = np.concatenate([np.repeat(bad[getattr(p, f.kind).arr, getattr(p, f.kind).ev], f.dim) for f in lin.factors])
    cost = np.where(out, 0.0, 2.0 * huber_rho(phys / sig))
    return np.array([float(np.sum(cost[arr == i])) for i in range(p.N)]), sig


def _doa_worse(first, result, features, models):
    """The arrays with clock terms in ``models`` whose DOAs fit ``result`` worse than the linear clock's
    ``first`` by more than the χ² of a pose (6 dof) at STRUCTURE_ALPHA: a clock term changes no DOA, it can
    only let the pose fitted to the TDOAs agree better with them. The DOAs of the arrivals the frontend doubts
    as the direct path's (:func:`doubted_arrivals`) do not count: a reflection's points at an image source, and
    an array refitted alone at the linear clock bends its pose to them (rendered office, an occluded array's 5 ms
    insert: its 12 undoubted DOAs' cost 268 at the linear clock, 3.6 with the true step; with its 8 reflection
    DOAs, 9878 against 9909, and the step was removed)."""
    if first is None or not any(n != EMITTER for n in models):
        return []
    doubted = doubted_arrivals(features)
    c0, sig = _doa_cost(first, features, doubted=doubted)
    c1, _ = _doa_cost(result, correct_features(features, models), sig, doubted)
    names = [str(n) for n in result["problem"].names]
    limit = float(chdtri(6, STRUCTURE_ALPHA))
    return [n for n in models if n in names and c1[names.index(n)] - c0[names.index(n)] > limit]


def _unstructured(result, features, models):
    """(array name, index) of the first component failing its structure test at ``result``, or None."""
    bad = _structure_failures(result, models, {}, correct_features(features, models))
    if not bad:
        return None
    name, kind, time = bad[0]
    return name, next(k for k, c in enumerate(models[name]) if _key(c) == (kind, time))


def persistence(result, models, features=None):
    """{(array name, k): the χ² of component k that no PERSIST_EVENTS consecutive events of its clock carry
    (:func:`persistent_drop`)}, in the joint problem linearised at a ``result`` solved with ``models`` (the
    features corrected by them: ``features``, every row counted), each component against the others and every
    parameter, rows Huber-weighted, in its clock's rows' robust scale (:func:`spread`); {} when the problem is
    too large. The per-array scan proposes a component at a fit its fault bent (:func:`best_component`):
    this judges it where the fit is not."""
    from .problem import make_layout
    from .solver import linearise

    from .clockscan import Projector

    p, st = _every_row(result, features), result["state"]
    lay = make_layout(p)
    if lay.n > SCAN_MAX:
        return {}
    lin = linearise(p, st, lay, active_kinds(p), dense=False)
    E, keys = component_columns(p, lin.factors, models)
    index = {**{str(n): j for j, n in enumerate(p.names)}, EMITTER: -1}
    doubted = doubted_arrivals(features) if features is not None else frozenset()
    out = {}
    solved = _solved_rows(result, lin.factors)
    for col, (name, k) in enumerate(keys):
        if models[name][k].kind == "arrival":
            continue
        sw, scale = _robust_weights(result, lin, p, own=name)
        sizes = [c.value for c in models[name] if c.kind == "step"]
        sw = sw * np.maximum(solved, _witnesses(result, lin, p, index[name], scale, doubted, sizes))   # (as
        # :func:`structure_test`)
        A, prior = _with_nuisance(result, lin, lay, np.delete(E, col, axis=1), sw)
        pr = Projector(A, lay, prior)
        r0 = (lin.r - models[name][k].value * E[:, col]) * sw
        rp, bp = pr.resid(r0), pr.resid(E[:, col] * sw)
        # (bᵀ P b and bᵀ P r: a nuisance's prior rows hold part of the projections, not the rows' |P b|²)
        bb, br = float(E[:, col] * sw @ bp), float(E[:, col] * sw @ rp)
        own = (_own_rows(p, lin.factors, index[name]) > 0) & (sw > 0)
        e = rp - bp * (br / max(bb, 1e-300))
        scale_i = max(scale, spread(e[own] / sw[own])) if own.any() else scale
        ids, groups = (_event_rows(p, lin.factors, own, ids=True) if name != EMITTER
                       else (None, _array_rows(p, lin.factors, own)))
        hat = pr.hat_of(np.flatnonzero(own))   # (the groups are own rows: indices into them)
        pos = np.cumsum(own) - 1
        by_event = [pos[g] for g in _event_rows(p, lin.factors, own)] if name == EMITTER else None
        out[(name, k)] = clock_persistence(p, lin.factors, index[name], models[name][k], [pos[g] for g in groups],
                                           hat, rp[own], bp[own], bb=bb, br=br,
                                           ids=ids, doubted=doubted, events=by_event) / scale_i ** 2
    return out


def _unpersistent(result, features, models):
    """(array name, index) of the component whose :func:`persistence` falls furthest short of PERSIST_CHI2, or
    None (each was chosen by a scan at its multiplicity: this is one more test of it). Ties (two terms of one
    clock that a leave-out leaves alike, both at 0: a hinge near the end and a step with one event after it,
    rendered lab seed 21) go to the one with the smaller joint (value / σ)²: the other is what the rows ask for."""
    short = [((chi2 - PERSIST_CHI2, _z2(models[key[0]][key[1]])), key)
             for key, chi2 in persistence(result, models, correct_features(features, models)).items()
             if chi2 < PERSIST_CHI2]
    return min(short)[1] if short else None


def _z2(c):
    """A component's joint (value / σ)² (infinite where it has no σ yet)."""
    return (c.value / c.std) ** 2 if c.std else np.inf


def _distrusted(result):
    """The arrays whose rows say nothing about the others' clocks: dropped as unreliable, or named by the
    verdict as inconsistent (their rows bend the sources, and a scan of the others would read that bend as
    their clocks) — the named ones only while they are fewer than half the other arrays (a fault most arrays
    show is the reference's clock, seen from each). Arrays named only as short of the precision target
    (report ``precision``: their rows agree with the rest, the data just determine them loosely) are not."""
    out = set(_unreliable(result))
    report = result.get("report") or {}
    flagged = set((report.get("verdict") or {}).get("flagged_arrays") or ()) - \
        {a["array"] for a in (report.get("precision") or {}).get("arrays", ())}
    n_others = len(result["problem"].names) - 1
    return out | flagged if len(out | flagged) < 0.5 * n_others else out


def _unreliable(result):
    return list((result.get("report") or {}).get("unreliable_arrays") or result.get("unreliable_arrays") or [])


def _weakest(p, models):
    """(array name, index) of the component with the most negative (value/σ)² − penalty, or None; first, one
    implausible or refined to a σ of exactly 0: every row its column touches is out of the solve (screened as
    doubted, or an outlier), so the solve's data say nothing of it and it moves nothing but the rows left out
    (rendered deploy dev 513: a 6.93 ms step of the reference proposed from A1's TDOA-M alone, whose rows after
    it were all doubted reflections, kept with σ 0.0 µs, the elimination skipping it for want of a σ)."""
    sizes = family_sizes(p.t)
    index = {str(n): i for i, n in enumerate(p.names)}
    worst, where = 0.0, None
    duration = float(np.ptp(p.t))
    for name, comps in models.items():
        i = index.get(name, -1)
        n = len(p.tdoa_s.val) if i < 0 else int(np.sum(p.tdoa_s.arr == i)) + int(np.sum(p.tdoa_m.arr == i))
        for k, c in enumerate(comps):
            if not c.plausible(duration):
                return name, k
            if c.std == 0.0 and c.kind != "arrival":
                return name, k   # (refined to a σ of 0: no row the solve uses holds it, :func:`refine`)
            if not c.std:
                continue
            m = (c.value / c.std) ** 2 - penalty(c.kind, n, p.N + 1, sizes)
            if m < worst:
                worst, where = m, (name, k)
    return where


# ----------------------------------------------------------------------------------------------- joint step
DENSE_MAX = 4000   # parameters: above this the components' σ are conditional (the rest held), no joint std


def _outlier_mask(fs, outliers):
    """{kind: keep per residual} from report-style outlier records (type, line), as ``assess.rebuild``."""
    flagged = {}
    for o in outliers or []:
        flagged.setdefault(o["type"], set()).add(int(o["line"]))
    return {f.kind: ~np.isin(np.asarray(f.row), list(flagged[f.kind])) for f in fs if f.kind in flagged}


def _kept_rows(result, fs):
    """1 for each stacked residual row of the factors ``fs`` the solve kept, 0 for those it screened out."""
    outliers = result["outliers"] if "outliers" in result else (result.get("report") or {}).get("outliers")
    mask = _outlier_mask(fs, outliers)
    keep = [np.ones(len(f.r), bool) if f.kind not in mask else
            (mask[f.kind] if len(mask[f.kind]) == len(f.r) else np.repeat(mask[f.kind], f.dim)) for f in fs]
    return np.concatenate(keep).astype(float) if keep else np.zeros(0)


def _solved_rows(result, fs):
    """1 for each stacked residual row of the factors ``fs`` (of every row, :func:`_every_row`) that
    the solve of ``result`` used: in its problem (not screened out by a frontend flag) and not an outlier."""
    q = result["problem"]
    out = []
    for f in fs:
        used = getattr(getattr(q, f.kind, None), "row", None)
        if used is None or len(f.row) * f.dim != len(f.r):
            out.append(np.ones(len(f.r), bool))
        else:
            out.append(np.repeat(np.isin(f.row, used), f.dim))
    return (np.concatenate(out) if out else np.zeros(0, bool)) * _kept_rows(result, fs)


def _own_rows(p, fs, i):
    """The stacked residual rows of the factors ``fs`` that clock i stamps: array i's TDOA-S and TDOA-M (the
    reference's: its TDOA-S and every TDOA-M), the emitter's (i = -1): every TDOA-S."""
    out = []
    for f in fs:
        arr = getattr(p, f.kind).arr if f.kind in ("tdoa_s", "tdoa_m") else None
        if arr is None or len(arr) != len(f.r):
            out.append(np.zeros(len(f.r), bool))
        elif i < 0:
            out.append(np.full(len(f.r), f.kind == "tdoa_s"))
        else:
            out.append((arr == i) | (f.kind == "tdoa_m" and i == p.ref))
    return np.concatenate(out).astype(float) if out else np.zeros(0)


def _doubted_table(p, doubted):
    """(N, E) bool: whether array i's arrival at the problem ``p``'s event k is one the frontend doubts as the direct
    path's (``doubted``: :func:`doubted_arrivals`, (array name, event id) pairs)."""
    row = {str(n): i for i, n in enumerate(p.names)}
    col = {int(e): k for k, e in enumerate(p.events)}
    out = np.zeros((len(row), len(col)), bool)
    at = [(row[n], col[e]) for n, e in doubted if n in row and e in col]   # (the doubted pairs, not every cell)
    if at:
        out[tuple(np.transpose(at))] = True
    return out


def _doubted_rows(p, fs, doubted):
    """1 for each stacked residual row of the factors ``fs`` that holds an arrival the frontend doubts as the
    direct path's (``doubted``: :func:`doubted_arrivals`; a TDOA-M holds its array's and the reference's, a
    TDOA-S its array's at both of its events)."""
    bad = _doubted_table(p, doubted)
    out = []
    for f in fs:
        rows = getattr(p, f.kind, None)
        if f.kind == "tdoa_m" and len(rows.arr) == len(f.r):
            out.append(bad[rows.arr, rows.ev] | bad[p.ref, rows.ev])
        elif f.kind == "tdoa_s" and len(rows.arr) == len(f.r):
            out.append(bad[rows.arr, rows.a] | bad[rows.arr, rows.b])
        else:
            out.append(np.zeros(len(f.r), bool))
    return np.concatenate(out) if out else np.zeros(0, bool)


SHIFT_MATCH = 0.1   # a doubted arrival off by a step's size to this share of it is shifted by that clock (wider: TDOA-S
# rows between two reflections, differences of 15-20 ms detours, fell in the band of a 5 ms step and testified)


def _witnesses(result, lin, p, i, scale, doubted, sizes=()):
    """The clock i's own rows that testify in the joint tests of its components at ``result`` (solved with
    them), as a 0/1 weight on the stacked rows (:func:`_own_rows`): every one the solve used, and those it
    left out (screened, outliers) but for the arrivals the frontend doubts (``doubted``) that the model leaves
    beyond Huber's reach (HUBER_K × ``scale``, in whitened units). A doubted arrival the clock's terms fit is
    a clock-shifted direct path (a step inside a run of doubted events: its evidence); one they leave ms off is a
    reflection (an occluded office array's reflection-only arrivals, 16-19 ms late in 8 of its 20 events), whose
    excess path is no clock's: under Huber's weight it read as a 200σ misfit of every row group and failed a true
    5 ms step's structure test at χ² 1164 on 3 dof. One off by a step's size (``sizes``, s: the clock's steps; to
    SHIFT_MATCH of it) either way is a clock-shifted arrival on the other side of that step and testifies against
    its placement (a step placed inside a run of doubted events, early: diag_doubted_step 570-579, 4 of 10
    misplaced so)."""
    own = _own_rows(p, lin.factors, i)
    if not doubted or i < 0:
        return own
    reach = HUBER_K * scale
    far = _doubted_rows(p, lin.factors, doubted) & (np.abs(lin.r) > reach)
    sig = np.concatenate([np.broadcast_to(f.row_sigma, len(f.r)) for f in lin.factors]) if lin.factors else 1.0
    for c in sizes:   # (the size is an estimate: a 0.51 ms step sized ± 63 µs left such rows 30 µs beyond reach)
        off = np.minimum(np.abs(lin.r - c / sig), np.abs(lin.r + c / sig))
        far &= off > np.maximum(reach, SHIFT_MATCH * abs(c) / sig)
    return np.where(far & (_solved_rows(result, lin.factors) == 0), 0.0, own)


def _columns(p, fs, i, comps):
    """Whitened Jacobian columns (rows of the stacked factors ``fs``) of array i's components' coefficients
    (i = -1: the emitter's, every array's TDOA-S)."""
    if i < 0:
        return _emitter_columns(p, fs, comps)
    u = p.t
    B = np.zeros((sum(len(f.r) for f in fs), len(comps)))
    start = 0
    for f in fs:
        n = len(f.r)
        sig = np.broadcast_to(f.row_sigma, n)[:, None]
        if f.kind == "tdoa_s":
            rows = p.tdoa_s
            mine = rows.arr == i
            B[start:start + n][mine] = (basis_matrix(comps, u[rows.b[mine]])
                                        - basis_matrix(comps, u[rows.a[mine]])) / sig[mine]
        elif f.kind == "tdoa_m":
            rows = p.tdoa_m
            mine = np.ones(n, bool) if i == p.ref else rows.arr == i
            B[start:start + n][mine] = (-1.0 if i == p.ref else 1.0) * basis_matrix(comps, u[rows.ev[mine]]) / sig[mine]
        start += n
    return B


def _emitter_columns(p, fs, comps):
    """The emitter's columns: every array's TDOA-S (each TDOA-M, a difference at one emission, cancels)."""
    u = p.t
    B = np.zeros((sum(len(f.r) for f in fs), len(comps)))
    start = 0
    for f in fs:
        n = len(f.r)
        if f.kind == "tdoa_s" and comps:
            rows = p.tdoa_s
            sig = np.broadcast_to(f.row_sigma, n)[:, None]
            B[start:start + n] = (basis_matrix(comps, u[rows.b]) - basis_matrix(comps, u[rows.a])) / sig
        start += n
    return B


def component_columns(p, fs, models):
    """Whitened Jacobian columns of every component's coefficient (:func:`_columns`) and the (array name,
    component index) of each column."""
    index = {**{str(n): i for i, n in enumerate(p.names)}, EMITTER: -1}
    keys = [(name, k) for name, comps in models.items() for k in range(len(comps))]
    cols = [_columns(p, fs, index[name], comps) for name, comps in models.items() if comps]
    return (np.hstack(cols) if cols else np.zeros((sum(len(f.r) for f in fs), 0))), keys


def refine(result, models):
    """One joint Gauss–Newton step of the components' coefficients with every parameter of the solved
    ``result`` (on the corrected data), and the joint covariance.

    Returns (moved: a coefficient moved by more than REFIT_SIGMA σ, models with the new values and their
    1-σ, info for :func:`_apply_std`: the problem, layout and joint covariance of the other parameters)."""
    from .problem import make_layout
    from .solver import linearise

    p, st = result["problem"], result["state"]
    kinds = active_kinds(p)
    lay = make_layout(p)
    full = linearise(p, st, lay, kinds)
    outliers = result["outliers"] if "outliers" in result else result["report"]["outliers"]
    lin = linearise(p, st, lay, kinds, mask=_outlier_mask(full.factors, outliers))
    B, keys = component_columns(p, lin.factors, models)
    keep = lin.w > 0
    if lay.n > DENSE_MAX:
        return _conditional(lin, B, keep, keys, models)
    # the step: every row, Cauchy-weighted (rows flagged against a wrong component are evidence against it; a
    # row hundreds of σ off, e.g. a chirp lost in a dropped block, pulls nothing: Huber's weight let it pull a
    # 50 ms step's size by 5σ)
    r = full.r
    scale = max(1.0, 1.4826 * float(np.median(np.abs(r[keep])))) if keep.any() else 1.0
    sw = 1.0 / np.sqrt(1.0 + (r / (HUBER_K * scale)) ** 2)
    step = _normal_solve(_weighted(lin.J, B, sw), None, -r * sw)
    # the covariance: the estimator's rows (outliers out), as its own error bars, with a moving source's velocity
    # error (its nuisance columns, as the scans; not in the step: the solve that follows does not model it, and a
    # step toward the model with it made the sizes of test_clocks' moving step swing by ±5σ from solve to solve)
    sw = np.where(keep, np.sqrt(np.maximum(lin.w, 0.0)), 0.0)
    cov = _normal_covariance(*_with_nuisance(result, lin, lay, B, sw))
    nb = lay.n + B.shape[1]
    dc, sd = step[lay.n:nb], np.sqrt(np.maximum(np.diag(_sandwich(result, lin, lay, B, sw))[lay.n:nb], 0.0))
    # (moved: against the σ the rows resolve it to, without the velocity error, which no solve moves: a size left
    # 10 µs off within its sandwich σ tipped a moving session's array over the solve's consistency test, seed 8)
    resolved = np.sqrt(np.maximum(np.diag(cov)[lay.n:nb], 0.0))
    return _update(models, keys, dc, sd, resolved) + ({"problem": p, "layout": lay, "cov": cov[:lay.n, :lay.n],
                                             "rows": _with_nuisance(result, lin, lay, B[:, :0], sw)},)


def _sandwich(result, lin, lay, B, sw):
    """The covariance of the fit's own parameters and the components' sizes as they are estimated (the solve and
    :func:`refine`'s step weigh the rows as stated, without the velocity nuisance) under the errors as they are:
    H + G Gᵀ, H = (AᵀA)⁻¹ of the weighted rows A = [J B] and G = H Aᵀ V their response to a moving source's
    velocity error V (:func:`_velocity_columns`; the error bars' ``uncertainty.sandwich_covariance`` likewise).
    The nuisance-projected covariance (:func:`_with_nuisance`) is that of an estimate that models the nuisance,
    which this one does not: on test_motion_noise's moving scene it stated 2-8 µs for 2 and 20 ms steps
    sized 10-90 µs off (5-15σ)."""
    A = _weighted(lin.J, B, sw)
    H = _normal_covariance(A)
    V = _velocity_columns(result, lin, lay)
    if V is None:
        return H
    G = H @ np.asarray((A.T @ (scipy.sparse.diags(sw) @ V)).todense())
    return H + G @ G.T


def _scaled_normal(A, prior=None):
    """(Jacobi-scaled AᵀA (+ diag(prior): unit-σ prior rows on some columns, a nuisance's; dense), the scale d)
    of a sparse A: no dense rows × n matrix."""
    H = (A.T @ A).toarray() + (0.0 if prior is None else np.diag(prior))
    d = np.sqrt(np.maximum(np.diag(H), 0.0))
    d = np.where(d > 0, d, 1.0)
    return H / d[:, None] / d[None, :], d


def _normal_solve(A, prior, y):
    """The least-squares solution of A x ≈ y (A sparse; ``prior``: :func:`_scaled_normal`) by its scaled normal
    equations; the minimum-norm one (a symmetric pseudo-inverse, as ``lstsq``) where they are singular (a
    direction no row fixes)."""
    Hs, d = _scaled_normal(A, prior)
    return np.linalg.pinv(Hs, hermitian=True) @ ((A.T @ y) / d) / d


def _normal_covariance(A, prior=None):
    """(AᵀA)⁻¹ as :func:`calib.estimator.uncertainty.covariance` gives it (pseudo-inverse of the Jacobi-scaled
    normal matrix; a Cholesky inverse is no substitute: near-singular directions made a 20 ms step's σ 98 s), from
    a sparse A (its symmetric eigendecomposition, not an SVD of the rows); ``prior``: :func:`_scaled_normal`."""
    Hs, d = _scaled_normal(A, prior)
    return np.linalg.pinv(Hs, hermitian=True) / d[:, None] / d[None, :]


def _conditional(lin, B, keep, keys, models):
    """Large problems: the components' step and σ with the other parameters held (no joint covariance)."""
    Bk = B[keep] * np.sqrt(lin.w[keep])[:, None]
    cov = np.linalg.pinv(Bk.T @ Bk)
    dc = -cov @ (Bk.T @ (lin.r[keep] * np.sqrt(lin.w[keep])))
    return _update(models, keys, dc, np.sqrt(np.maximum(np.diag(cov), 0.0))) + (None,)


def _update(models, keys, dc, sd, resolved=None):
    moved = bool(np.any(np.abs(dc) > REFIT_SIGMA * np.maximum(sd if resolved is None else resolved, 1e-300)))
    out = {name: list(comps) for name, comps in models.items()}
    for col, (name, k) in enumerate(keys):
        c = out[name][k]
        out[name][k] = c.with_value(c.value + dc[col], float(sd[col]))
    return moved, out


def _apply_std(result, info):
    """The arrays' and sources' 1-σ columns (and calibration.json's array covariance) widened by the components'
    uncertainty: each parameter's σ times (its joint σ with the components / its σ without them), both of the
    estimator's rows as weighted (``info`` from :func:`refine`). The solve's own σ are its honest ones (the rows'
    σ² factors, shared arrivals, a moving source's velocity error: ``uncertainty.honest_covariance``), which the
    plain joint covariance lacks: put in their place it held featsim seed 6 of test_motion_noise's arrays at
    0.9 mm, 2-10 cm off. A component only adds uncertainty: no σ is made smaller (an unreliable array's stay
    empty)."""
    if info is None or "arrays" not in result:
        return
    from .assess import labelled_array_covariance
    from .uncertainty import std_from_cov

    p, lay = info["problem"], info["layout"]
    plain = np.diag(_normal_covariance(*info["rows"]))[:lay.n]
    ratio = np.sqrt(np.divide(np.diag(info["cov"]), plain, out=np.ones_like(plain), where=plain > 0))
    ratio = np.where(np.isfinite(ratio), np.maximum(ratio, 1.0), 1.0)
    widen = std_from_cov(p, lay, np.diag(ratio ** 2))
    if result.get("array_covariance") is not None:   # calibration.json's, widened as the std columns
        labels, cov = result["array_covariance"]
        names, block = labelled_array_covariance(p, lay, np.diag(ratio))
        by_label = dict(zip(names, np.diag(block)))
        d = np.array([by_label.get(lab, 1.0) for lab in labels])
        result["array_covariance"] = (labels, np.asarray(cov) * np.outer(d, d))
    arrays, sources = result["arrays"], result["sources"]
    for a in ARRAY_PARAMS:
        v = np.asarray(widen[a.key]).reshape(len(arrays), -1)
        for k, col in enumerate(a.std_columns):
            if col in arrays:
                arrays[col] = arrays[col].to_numpy(float) * np.where(np.isfinite(v[:, k]), v[:, k], 1.0)
    for k, c in enumerate("xyz"):
        col = f"{c}_std"
        if col in sources:
            sources[col] = sources[col].to_numpy(float) * np.where(np.isfinite(widen["s"][:, k]), widen["s"][:, k], 1.0)


# ----------------------------------------------------------------------------------------------- bound
JUMP_SIGMAS = 5.0   # a TDOA-S this many σ (its own and the odometry's) beyond what the speaker's move allows
# ... and beyond this many times the odometry's move: odometry drifts, and a speaker offset from the robot's
# odometry point moves more than it on a turn (rendered rooms: TDOA-S up to 1.9x the odometry's move / c)
JUMP_MOVES = 2.0


def impossible_jumps(features):
    """Geometry-free: each array's TDOA-S that no source move explains. Between consecutive events a → b the
    array's arrival interval is (1 + δ)(t_b − t_a) + (d_b − d_a)/c with |d_b − d_a| ≤ |s_b − s_a| (the
    triangle inequality), the speaker's move from odometry. An interval further off than that (δ from the
    array's median ratio; JUMP_MOVES × the odometry's move, and JUMP_SIGMAS σ of the TDOA, odometry and that
    ratio allowed) holds a jump of the array's clock (dropped or inserted samples) or a mis-detected chirp. It
    needs no fit: it names a reference's step that leaves the linear solve in no basin at all.

    Only the rows the estimator keeps count (:func:`calib.estimator.screen.screen_rows`: the frontend's
    reflection-only rows, 10-25 ms late in rendered rooms, are out; an array mostly so is named elsewhere).

    Returns [{array, after_event, before_event, size (s: the excess interval), allowed (s)}], largest first."""
    from .screen import screen_rows

    features, record = screen_rows(features)
    ev = features["events"].sort_values("event")
    meta = features.get("meta") or {}
    c = float(meta.get("speed_of_sound", 343.0))
    sig_t = float(meta.get("sigma_tdoa") or 1e-4)
    sig_o = float(meta.get("sigma_odo") or 0.01)
    ids = ev["event"].to_numpy(int)
    cols = [k for k in ("odom_x", "odom_y", "odom_z") if k in ev]
    ts = features["tdoa_s"]
    out = []
    if len(cols) != 3 or not len(ts):
        return out
    t_emit, xyz = ev["t_emit"].to_numpy(float), ev[cols].to_numpy(float)   # rows in event order
    for name, rows in ts.groupby("array", sort=False):
        if str(name) in record["kept_doubted"]:
            continue
        a = np.searchsorted(ids, rows["from_event"].to_numpy(int))   # rows of events.csv (vectorised: 5e5 rows
        b = np.searchsorted(ids, rows["to_event"].to_numpy(int))     # at 100 arrays × 5000 events)
        dt, move = t_emit[b] - t_emit[a], np.linalg.norm(xyz[b] - xyz[a], axis=1)
        use = dt > 0
        if use.sum() < MIN_EVENTS:
            continue
        ratio = rows["tdoa"].to_numpy(float)[use] / dt[use]
        g = float(np.median(ratio))
        g_sd = 1.4826 * float(np.median(np.abs(ratio - g))) / np.sqrt(use.sum())
        e = rows["tdoa"].to_numpy(float) - g * dt
        allowed = JUMP_MOVES * move / c + JUMP_SIGMAS * (np.sqrt(2) * (sig_t + sig_o / c) + g_sd * np.abs(dt))
        for k in np.flatnonzero(use & (np.abs(e) > allowed)):
            out.append({"array": str(name), "after_event": int(ids[a[k]]), "before_event": int(ids[b[k]]),
                        "size": float(e[k]), "allowed": float(allowed[k])})
    return sorted(out, key=lambda j: -abs(j["size"]))


def _jump_text(j):
    return (f"{j['array']}: its arrivals jump {j['size'] * 1e3:+.3f} ms between events {j['after_event']} and "
            f"{j['before_event']}, more than the speaker's move there allows (at most {j['allowed'] * 1e3:.3f} ms): "
            "its clock jumped (samples dropped or inserted) or a chirp was mis-detected there")


# ----------------------------------------------------------------------------------------------- report
def _event_of(features):
    ev = features["events"]
    t0 = float(ev["t_emit"].iloc[0])
    return ev["event"].to_numpy(int), ev["t_emit"].to_numpy(float) - t0


def nominal_rate(drift, std=None):
    """A wrong nominal rate read from a fitted drift, or None: {ratio, header_hz, actual_hz (when the ratio
    matches two common rates), crystal_drift (what is left of the drift after that ratio)}."""
    if not np.isfinite(drift) or abs(drift) < RATE_ERROR_MIN:
        return None
    ratio = 1.0 + float(drift)
    pair = header_ratio(ratio, RATE_MATCH_TOL + 3.0 * float(std or 0.0))
    out = {"ratio": ratio, "header_hz": None, "actual_hz": None, "crystal_drift": None}
    if pair:
        out.update(header_hz=pair[0], actual_hz=pair[1], crystal_drift=ratio / (pair[1] / pair[0]) - 1.0)
    return out


def _rate_drifts(result):
    """Each array's drift to judge for a wrong nominal rate (NaN: not judged), and the common ratio of a
    wrong time base (or None). Against the emission times, an array runs off by a ratio no crystal gives
    when its own header is wrong — or when the emission times are scaled, and then every array (the
    reference too) runs off by the same ratio: that is named once, as the time base, not per array."""
    st, ref = result["state"], int(result["problem"].ref)
    g = 1.0 + np.asarray(st.drift, float)
    off = np.abs(g - 1.0) >= RATE_ERROR_MIN
    same_as_ref = np.abs(g / g[ref] - 1.0) < RATE_ERROR_MIN
    if off[ref] and np.mean(same_as_ref) > 0.5:   # most arrays agree with the reference: the time base
        return np.where(same_as_ref, 0.0, g / g[ref] - 1.0), float(g[ref])
    return g - 1.0, None


def _base_text(ratio):
    return (f"time base: the arrays' clocks run at {ratio:.5f}× the emission times (events.csv t_emit), all "
            "alike: those times are scaled (or every stated sample rate is wrong); no clock model was fitted")


def _rate_text(name, nr):
    if nr["header_hz"]:
        return (f"{name}: wrong nominal sample rate: its clock runs at {nr['ratio']:.5f}× the stated rate, as a "
                f"{nr['actual_hz']} Hz board whose WAV says {nr['header_hz']} Hz (crystal drift after that: "
                f"{nr['crystal_drift'] * 1e6:+.0f} ppm); calibrated with that rate")
    return (f"{name}: wrong nominal sample rate: its clock runs at {nr['ratio']:.5f}× the stated rate "
            f"({(nr['ratio'] - 1) * 100:+.2f} %, no crystal drifts so far); calibrated with that rate")


def array_clock_entry(comps, events, u, drift, drift_std):
    """report.json ``clock.arrays[name]``: drift model, steps (between which events, size, σ), drift terms,
    the raw components (read back by :func:`models_from_report`) and a nominal-rate finding."""
    steps = []
    for c in comps:
        if c.kind != "step":
            continue
        before, after = u < c.time, u > c.time
        steps.append({"after_event": int(events[before][np.argmax(u[before])]) if before.any() else None,
                      "before_event": int(events[after][np.argmin(u[after])]) if after.any() else None,
                      "time": float(c.time), "size": float(c.value), "std": c.std,
                      "kind": "inserted" if c.value > 0 else "dropped"})
    terms = [c for c in comps if c.kind not in ("step", "arrival")]
    arrivals = [{"event": int(events[np.argmin(np.abs(u - c.time))]), "time": float(c.time), "size": float(c.value),
                 "std": c.std} for c in comps if c.kind == "arrival"]
    kinds = sorted({{"quadratic": "quadratic", "warmup": "warm-up"}.get(c.kind, "piecewise_linear") for c in terms})
    return {"drift_model": "+".join(kinds) if kinds else "linear", "steps": steps,
            "drift_terms": [_term_entry(c) for c in terms], "arrivals": arrivals,
            "components": [{"kind": c.kind, "time": c.time, "value": c.value, "std": c.std} for c in comps],
            "nominal_rate": nominal_rate(drift, drift_std)}


def _term_entry(c):
    """report.json's entry of a drift term."""
    if c.kind == "quadratic":
        return {"kind": "quadratic", "slope": c.value, "std": c.std}
    if c.kind == "warmup":   # (calib.clock's exponential term)
        return {"kind": "exp", "amplitude": c.value, "time_constant": c.time, "std": c.std}
    return {"kind": "hinge", "time": c.time, "change": c.value, "std": c.std}


def models_from_report(report):
    """{array name: [Component]} from report.json ``clock`` (empty when absent: the linear clock)."""
    clock = (report or {}).get("clock") or {}
    entries = {**(clock.get("arrays") or {}), EMITTER: clock.get("emitter") or {}}
    return {name: [Component(c["kind"], float(c["time"]), float(c["value"]), c.get("std"))
                   for c in e.get("components") or []] for name, e in entries.items() if e.get("components")}


def clock_report(result, features, models, rounds):
    """report.json ``clock``: per array its model (:func:`array_clock_entry`), the emitter's (emission times
    off by a common term), the findings, the detection rounds' records."""
    events, u = _event_of(features)
    st = result["state"]
    std = result["arrays"]["drift_std"].to_numpy(float) if "arrays" in result else np.full(len(st.drift), np.nan)
    arrays, findings = {}, []
    rates, base = _rate_drifts(result)
    taken = time_bases(features["meta"])   # arrays whose samples were read at another rate than their header's
    for i, name in enumerate(str(n) for n in features["meta"]["arrays"]):
        e = array_clock_entry(models.get(name, []), events, u, rates[i], std[i])
        e["sample_rate"], e["header_sample_rate"] = taken.get(name, (None, None))
        if e["nominal_rate"]:
            e["nominal_rate"]["relative_to"] = "emitter (events.csv t_emit)"
        arrays[name] = e
        for s in e["steps"]:
            sd = f", σ {s['std'] * 1e6:.1f} µs" if s["std"] is not None else ""
            findings.append(f"{name}: {abs(s['size']) * 1e3:.3f} ms of samples {s['kind']} between events "
                            f"{s['after_event']} and {s['before_event']}{sd} (modelled as a clock step)")
        if e["drift_model"] != "linear":
            findings.append(f"{name}: drift varies over the session (modelled as {e['drift_model']})")
        for a in e["arrivals"]:
            findings.append(f"{name}: its arrival at event {a['event']} is {abs(a['size']) * 1e3:.3f} ms "
                            f"{'late' if a['size'] > 0 else 'early'} against its clock (a chirp lost in dropped "
                            "samples, or mis-detected): modelled as that one arrival's error")
        if e["nominal_rate"]:
            findings.append(_rate_text(name, e["nominal_rate"]))
    if base is not None:
        findings.append(_base_text(base))
    findings += _ambiguities(rounds, models, events, u)
    emitter = array_clock_entry(models.get(EMITTER, []), events, u, 0.0, None)
    emitter.pop("nominal_rate")
    for s in emitter["steps"]:
        findings.append(f"emission times: the interval between events {s['after_event']} and {s['before_event']} is "
                        f"{abs(s['size']) * 1e3:.3f} ms {'longer' if s['size'] > 0 else 'shorter'} than events.csv "
                        f"says (every array sees it; modelled)")
    if emitter["drift_model"] != "linear":
        findings.append(f"emission times drift against events.csv (every array sees it; modelled as "
                        f"{emitter['drift_model']})")
    return {"selection": "auto" if rounds else "linear", "arrays": arrays, "emitter": emitter,
            "findings": findings, "detection": rounds}


def _ambiguities(rounds, models, events, u):
    """Findings for the rival proposals the data could not tell from a component still in ``models``."""
    def where(t):
        before, after = u < t, u > t
        return (f"between events {int(events[before][np.argmax(u[before])]) if before.any() else '-'} and "
                f"{int(events[after][np.argmin(u[after])]) if after.any() else '-'}")

    def text(name, kind, t, v):
        return f"{name}'s {kind} of {v * 1e3:+.3f} ms {where(t)}" if kind == "step" else f"{name}'s {kind} term"

    have = {(n, c.kind, round(c.time, 9)) for n, comps in models.items() for c in comps}
    out = []
    for rec in (r for rnd in rounds for r in rnd if "ambiguous" in r):
        (name, kind, t, v), *alts = rec["ambiguous"]
        if (name, kind, round(t, 9)) in have:
            out.append(f"{text(name, kind, t, v)} (modelled) explains the data as well as "
                       + " or ".join(text(*a) for a in alts) + ": the data cannot tell which clock it is")
    # a modelled step whose neighbouring intervals the scan could not tell from its own (:func:`_near_intervals`)
    for rec in (r for rnd in rounds for r in rnd if "near_intervals" in r):
        name, near = rec["array"], rec["near_intervals"]
        step = next((c for c in models.get(name, []) if c.kind == "step" and round(c.time, 9) == round(near["time"], 9)),
                    None)
        line = None if step is None else (f"{text(name, 'step', step.time, step.value)} (modelled) explains the data "
                                          f"as well as a step " + " or ".join(where(t) for t in near["others"])
                                          + ": the data cannot tell in which interval it stepped")
        if line is not None and line not in out:
            out.append(line)
    return out


def _attach_report(result, features, models, rounds, vetoed=None):
    """Put ``clock`` into the report (or the solution dict); a wrong nominal rate is a verdict reason.
    ``vetoed``: why no clock model was selected (:func:`calibrate_clocks`' ``clock_veto``), a finding."""
    block = clock_report(result, features, models, rounds)
    if vetoed:
        block["findings"].append(f"clock model not selected (linear clocks): {vetoed}")
    # jumps no source move explains, left after the modelled terms (:func:`impossible_jumps`)
    block["jumps"] = impossible_jumps(correct_features(features, models))
    block["findings"] += [_jump_text(j) for j in block["jumps"]]
    result["clock_models"] = models
    if "report" not in result:
        result["clock"] = block
        return
    rep = result["report"]
    rep["clock"] = block
    rates = [f for f in block["findings"] if "wrong nominal sample rate" in f or f.startswith("time base")]
    v = rep["verdict"]
    if rates:
        v["reasons"] = list(v.get("reasons") or []) + rates
        if v.get("status") == "ok":
            v["status"] = "suspect"
    if block["jumps"] and v.get("status") != "ok":   # what a failed or suspect result may come from
        v["reasons"] = list(v.get("reasons") or []) + [_jump_text(j) for j in block["jumps"]]
