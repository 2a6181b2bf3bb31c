"""An audio clock as a function of true time: local time ``L(t)`` and its inverse (docs/architecture.md).

``L(t) = τ + (1 + δ) u + Σ_terms E(u) + steps``, ``u = t − t0``: offset ``τ`` (local time at ``t0``), constant
drift ``δ`` (a wrong nominal rate included: a board running at f_true written as f_header has
``1 + δ = f_true / f_header``), drift terms that vary the rate over time (:data:`TERMS`), and steps:
sample blocks inserted (size > 0: the local time jumps forward by ``size`` at ``time``) or dropped (size < 0:
the local time stands still at ``time`` until the clock has run ``|size|`` on, then goes on ``|size|``
behind). ``L`` is monotone non-decreasing; :meth:`Clock.emitter` is its generalised inverse
``inf{t : L(t) >= T}`` (inside an inserted block: the step's time; on a dropped block's flat: its start).

One place for the simulators (``calib.pipeline.simulate.clocks`` draws the faults), the estimator's clock
models (``calib.estimator.clockmodel``) and the calibration reader (``calib.pipeline.formats.results``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Common audio sample rates (Hz): a fitted rate ratio near a ratio of two of them is a wrong header.
# (most common first: a ratio two pairs share, 44100/48000 = 22050/24000, names the first)
COMMON_RATES = (48000, 44100, 16000, 96000, 8000, 32000, 22050, 24000, 11025, 88200, 192000, 176400)
INVERSE_ITERATIONS = 200   # bisection steps of the inverse (stops at float resolution; 2^-200 of the bracket)


def _exp_term(u, amplitude, time_constant):
    """A warm-up: drift δ + amplitude·exp(−u/T) → ∫ = amplitude·T·(1 − exp(−u/T)) (u < 0: linear)."""
    return amplitude * time_constant * -np.expm1(-np.maximum(u, 0.0) / time_constant) + amplitude * np.minimum(u, 0.0)


def _quadratic_term(u, slope):
    """Drift changing linearly in time, δ + slope·u → ∫ = slope·u²/2."""
    return 0.5 * slope * u * u


def _hinge_term(u, time, change):
    """Drift changing by ``change`` at ``u = time`` (piecewise-linear clock) → change·max(0, u − time)."""
    return change * np.maximum(u - time, 0.0)


def _table_term(u, knots, values):
    """A tabulated extra local time (e.g. a random walk's integral), linear between knots, held outside."""
    return np.interp(u, np.asarray(knots, float), np.asarray(values, float))


# Drift terms by kind: the function of u (s since t0) and its parameter names (the clock's JSON form).
TERMS = {"exp": (_exp_term, ("amplitude", "time_constant")),
         "quadratic": (_quadratic_term, ("slope",)),
         "hinge": (_hinge_term, ("time", "change")),
         "table": (_table_term, ("knots", "values"))}

# The parameters of each term that are local time (or its rate): those a change of time base scales.
SCALED_PARAMS = {"exp": ("amplitude",), "quadratic": ("slope",), "hinge": ("change",), "table": ("values",)}


@dataclass(frozen=True)
class Step:
    """A block of samples inserted (size > 0, s of local time) or dropped (size < 0) at emitter ``time``
    (s since t0); ``std``: 1-σ of an estimated size (None when given)."""
    time: float
    size: float
    std: float | None = None


@dataclass(frozen=True)
class Term:
    """One drift term: ``kind`` of :data:`TERMS` and its parameters (names as TERMS lists them)."""
    kind: str
    params: dict = field(default_factory=dict)

    def __call__(self, u):
        fn, names = TERMS[self.kind]
        return fn(u, *(self.params[n] for n in names))


@dataclass(frozen=True)
class Clock:
    """Local time of an array as a function of emitter time t (s). See the module docstring."""
    offset: float = 0.0
    drift: float = 0.0
    t0: float = 0.0
    steps: tuple = ()
    terms: tuple = ()

    def continuous(self, t):
        """Local time without the steps."""
        u = np.asarray(t, float) - self.t0
        out = self.offset + (1.0 + self.drift) * u
        for term in self.terms:
            out = out + term(u)
        return out

    def local(self, t):
        """Local time(s) L(t) (s) of emitter time(s) t: monotone non-decreasing (see the module docstring)."""
        t = np.asarray(t, float)
        lc = self.continuous(t)
        out = lc.copy() if np.ndim(lc) else np.array(lc)
        for s in self.steps:
            after = t >= self.t0 + s.time
            if s.size >= 0:
                out = out + np.where(after, s.size, 0.0)
            else:   # dropped: the reading stands still until the clock has run |size| on
                run = lc - self.continuous(self.t0 + s.time)
                out = out - np.where(after, np.minimum(run, -s.size), 0.0)
        return out[()] if np.ndim(out) == 0 else out

    def rate(self, t):
        """dL/dt between steps (1 + δ + the terms' drift), by a central difference of the continuous part."""
        h = 1e-3
        return (self.continuous(np.asarray(t, float) + h) - self.continuous(np.asarray(t, float) - h)) / (2 * h)

    def sample(self, t, fs):
        """Sample index (float) of emitter time t on a WAV of nominal rate ``fs`` (local time × fs)."""
        return self.local(t) * fs

    def emitter(self, T):
        """Emitter time(s) of local time(s) T: inf{t : L(t) >= T} (bisection on a bracket from the linear part)."""
        T = np.asarray(T, float)
        g = 1.0 + self.drift
        span = sum(abs(s.size) for s in self.steps) + 1.0
        guess = self.t0 + (T - self.offset) / g
        extra = np.abs(self.continuous(guess) - (self.offset + g * (guess - self.t0))) / g
        lo, hi = guess - 2 * span - 2 * extra - 1.0, guess + 2 * span + 2 * extra + 1.0
        for _ in range(INVERSE_ITERATIONS):
            mid = 0.5 * (lo + hi)
            up = self.local(mid) >= T
            hi, lo = np.where(up, mid, hi), np.where(up, lo, mid)
            if np.all(hi - lo <= 4 * np.spacing(np.maximum(np.abs(hi), 1.0))):
                break
        return hi[()] if np.ndim(hi) == 0 else hi

    def extra(self, t):
        """L(t) − τ − (1 + δ)(t − t0): what the steps and drift terms add to the linear clock (s)."""
        u = np.asarray(t, float) - self.t0
        return self.local(t) - self.offset - (1.0 + self.drift) * u

    def scaled(self, r):
        """The same clock with every local time multiplied by ``r``: the samples of a clock counted at a rate
        ``f`` (local time n / f) read at a rate ``f / r`` (n · r / f); ``r = f_used / f_header`` gives an array
        taken at a measured rate on its header's time base. Offset, steps and terms scale by r, 1 + δ too."""
        r = float(r)
        terms = tuple(Term(d.kind, {k: (np.asarray(v, float) * r if k in SCALED_PARAMS[d.kind] else v)
                                    for k, v in d.params.items()}) for d in self.terms)
        return Clock(r * self.offset, r * (1.0 + self.drift) - 1.0, self.t0,
                     tuple(Step(s.time, r * s.size, None if s.std is None else r * s.std) for s in self.steps), terms)

    def to_dict(self):
        """JSON form: {offset, drift, t0, steps: [{time, size, std}], terms: [{kind, ...params}]}."""
        return {"offset": float(self.offset), "drift": float(self.drift), "t0": float(self.t0),
                "steps": [{"time": float(s.time), "size": float(s.size), "std": s.std} for s in self.steps],
                "terms": [{"kind": d.kind, **{k: _plain(v) for k, v in d.params.items()}} for d in self.terms]}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`to_dict` (missing keys: no steps / terms)."""
        steps = tuple(Step(float(s["time"]), float(s["size"]), s.get("std")) for s in d.get("steps") or ())
        terms = []
        for e in d.get("terms") or ():
            kind = e["kind"]
            if kind not in TERMS:
                raise ValueError(f"unknown clock term {kind!r} (known: {', '.join(TERMS)})")
            terms.append(Term(kind, {n: e[n] for n in TERMS[kind][1]}))
        return cls(float(d.get("offset", 0.0)), float(d.get("drift", 0.0)), float(d.get("t0", 0.0)), steps,
                   tuple(terms))


def _plain(v):
    return np.asarray(v, float).tolist() if np.ndim(v) else float(v)


def header_ratio(ratio, tol):
    """(header, actual) of two common rates (:data:`COMMON_RATES`) whose ratio actual/header is closest to
    ``ratio`` and within ``tol`` of it, or None."""
    pairs = [(h, a) for h in COMMON_RATES for a in COMMON_RATES if a != h and abs(a / h - ratio) <= tol]
    return min(pairs, key=lambda p: abs(p[1] / p[0] - ratio)) if pairs else None


def time_bases(meta):
    """{array: (sample_rate, header_sample_rate)} (Hz) of the arrays whose local time counts WAV samples at
    another rate than their header's (features meta ``sample_rates``: declared in session.toml or measured),
    with the header's rate (meta ``header_sample_rates``; for features before it, ``header_rates``' ``header``
    of a measured one; None: unknown). Their local time is WAV sample / sample_rate."""
    headers = {**{n: f.get("header") for n, f in (meta.get("header_rates") or {}).items()},
               **(meta.get("header_sample_rates") or {})}
    return {n: (int(r), None if headers.get(n) is None else int(headers[n]))
            for n, r in (meta.get("sample_rates") or {}).items()}


def header_time_base(offset, drift, scale, ref_scale, reference_offset):
    """(offset, drift) of an array's linear clock on its header's time base (WAV sample / header rate): the
    calibration's, on the time base of the rate its samples were taken at, composed with ``scale`` = that rate /
    its header's (``ref_scale``: the reference array's). With L = r·L' (r = ``scale``), 1 + δ = r(1 + δ') and,
    the offsets relative to the reference's local time τ_ref' at t0 (``reference_offset``, on the reference's
    taken time base), offset = r·offset' + (r − r_ref)·τ_ref'. Arrays (numpy) broadcast."""
    r, r_ref = np.asarray(scale, float), np.asarray(ref_scale, float)
    return r * np.asarray(offset, float) + (r - r_ref) * reference_offset, r * (1.0 + np.asarray(drift, float)) - 1.0
