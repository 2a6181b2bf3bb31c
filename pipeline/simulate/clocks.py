"""Clock faults of real audio interfaces, for both simulators (``featsim`` and the room renderer).

A fault description (a dict, the scenario/preset form) becomes a :class:`calib.clock.Clock`: local time as a
function of true time with its inverse. Faults (all optional, combined):

``steps``      blocks of samples dropped (size < 0) or inserted (size > 0), each ``{"time": s, "size": s}``
               (time in s since t0; ``{"size": s}`` alone: placed in a random interval between two events);
``warmup``     a warm-up: the drift starts ``amplitude`` away from its final value and settles
               exponentially, ``{"amplitude": 3e-6, "time_constant": 60.0}``;
``walk``       a slow random walk of the drift, ``{"sigma": per √s, "step": s}`` (seeded);
``rate``       a wrong nominal rate: ``{"header": 48000, "actual": 44100}`` (the WAV says 48 kHz, the board
               runs at 44.1 kHz: the local clock runs at 44100/48000) or ``{"error": 0.01}`` (1 % fast).

The constant drift δ the scene draws and the rate error combine into one drift
``1 + δ_total = (actual / header)(1 + δ)``, the truth's ``drift``; the full clock goes to the truth's ``clocks``
(:func:`clock_record`) so ``calib evaluate`` can score a clock model against it.

Presets (:data:`CLOCK_PRESETS`) name the published cases (USB/ESP boards dropping blocks, warm-up, CHiME-6's
mid-session rate change, a 44.1 kHz board written as 48 kHz).
"""
from __future__ import annotations

import numpy as np

from calib.clock import Clock, Step, Term
from calib.geometry import local_time
from calib.tables import flag_text

WALK_STEP = 1.0   # s between the random walk's drift increments (default)

CLOCK_PRESETS = {
    "drop": {"steps": [{"size": -0.020}]},                            # one 20 ms block dropped mid-session
    "insert": {"steps": [{"size": 0.005}]},                           # 5 ms of samples inserted
    "esp": {"steps": [{"size": -508e-6}]},                            # an ESP8266 board's 508 µs jump
    "warmup": {"warmup": {"amplitude": 3e-6, "time_constant": 60.0}},
    "walk": {"walk": {"sigma": 2e-8}},                                # ~0.1 ppm per minute of drift wander
    "rate44k": {"rate": {"header": 48000, "actual": 44100}},
    "rate1pct": {"rate": {"error": 0.01}},
    "rate1000ppm": {"rate": {"error": 1e-3}},
}
KNOWN_KEYS = {"steps", "warmup", "walk", "rate"}


def resolve(faults):
    """A fault dict from a preset name, a dict, or None (no faults). Raises ValueError naming bad keys."""
    if faults is None:
        return {}
    if isinstance(faults, str):
        if faults not in CLOCK_PRESETS:
            raise ValueError(f"unknown clock preset {faults!r} (known: {', '.join(CLOCK_PRESETS)})")
        return dict(CLOCK_PRESETS[faults])
    bad = set(faults) - KNOWN_KEYS
    if bad:
        raise ValueError(f"unknown clock fault key(s) {sorted(bad)} (known: {sorted(KNOWN_KEYS)})")
    return dict(faults)


def rate_ratio(rate):
    """actual / header rate of a ``rate`` fault (1.0 when absent)."""
    if not rate:
        return 1.0
    if "error" in rate:
        return 1.0 + float(rate["error"])
    return float(rate["actual"]) / float(rate["header"])


def fault_clock(offset, drift, faults, *, event_times, rng, t0=0.0):
    """The :class:`Clock` of one array: offset τ, crystal drift δ, and ``faults`` (:func:`resolve` form).

    event_times : (K,) emission times − t0 (s): a step without a time goes in a random interval between two
    events (at its middle), a random walk is drawn up to the last one. rng : numpy Generator (steps, walk).
    """
    faults = resolve(faults)
    g = rate_ratio(faults.get("rate")) * (1.0 + drift)
    t = np.asarray(event_times, float)
    steps = []
    for s in faults.get("steps") or ():
        if "time" in s:
            time = float(s["time"])
        else:
            k = int(rng.integers(0, len(t) - 1))
            time = 0.5 * (t[k] + t[k + 1])
        steps.append(Step(time, float(s["size"])))
    terms = []
    if faults.get("warmup"):
        w = faults["warmup"]
        terms.append(Term("exp", {"amplitude": float(w["amplitude"]), "time_constant": float(w["time_constant"])}))
    if faults.get("walk"):
        terms.append(_walk_term(faults["walk"], t[-1] if len(t) else 0.0, rng))
    return Clock(offset=float(offset), drift=float(g - 1.0), t0=float(t0), steps=tuple(sorted(steps, key=lambda s: s.time)),
                 terms=tuple(terms))


def _walk_term(walk, duration, rng):
    """A random walk of the drift (std ``sigma`` per √s) integrated to an extra local time, as a table."""
    h = float(walk.get("step", WALK_STEP))
    n = int(np.ceil(max(duration, h) / h)) + 2
    knots = h * np.arange(n)
    d = np.concatenate([[0.0], np.cumsum(rng.normal(0.0, float(walk["sigma"]) * np.sqrt(h), n - 1))])
    values = np.concatenate([[0.0], np.cumsum(0.5 * (d[1:] + d[:-1]) * h)])   # ∫ drift, trapezoids
    return Term("table", {"knots": knots, "values": values})


def clock_record(clock, faults=None, event_times=None):
    """The truth's record of one array's clock: the clock's JSON form + the nominal-rate ratio, and the
    session's emission times (s since t0, ``event_times``: events 0, 1, …) that ``calib evaluate`` scores the
    clock at (which interval a step lies in, the local-time error over the session)."""
    faults = resolve(faults)
    out = {**clock.to_dict(), "rate_ratio": rate_ratio(faults.get("rate"))}
    if event_times is not None:
        out["event_times"] = np.asarray(event_times, float).tolist()
    return out



# ----------------------------------------------------------------------------------------------- room simulator
def attach(sc, faults, seed):
    """Give each array of a normalised room scenario ``sc`` with faults (``faults``: the scenario's
    ``clock_faults``, {array name: preset name or fault dict}) its clock (``a["clock"]``) and that clock's
    drift (a rate error included), in place. Raises InputError naming a bad entry."""
    from calib.errors import InputError

    faults = faults or {}
    if not isinstance(faults, dict):
        raise InputError("scenario: clock_faults must map array names to clock faults")
    names = [a["name"] for a in sc["arrays"]]
    for name in faults:
        if name not in names:
            raise InputError(f"scenario: clock_faults names unknown array {name!r} (arrays: {', '.join(names)})")
    t = np.asarray(sc["t_emit"], float)
    for k, a in enumerate(sc["arrays"]):
        if a["name"] not in faults:
            continue
        try:
            clk = fault_clock(a["tau"], a["drift"], faults[a["name"]], event_times=t - t[0],
                              rng=np.random.default_rng([int(seed), 28, k]), t0=float(t[0]))
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise InputError(f"scenario: clock_faults.{a['name']}: {exc}") from None
        a["clock"], a["drift"] = clk, clk.drift
    return sc


def local(a, t, t0):
    """Local time of array ``a`` (normalised scenario entry) at true time(s) t: its fault clock if it has
    one, else ``(1 + δ)(t − t0) + τ``."""
    clk = a.get("clock")
    return clk.local(t) if clk is not None else local_time(t, a["tau"], a["drift"], t0)


def true_time(a, L, t0):
    """True (emitter) time(s) of array ``a``'s local time(s) L, the inverse of :func:`local`: its fault
    clock's (:meth:`calib.clock.Clock.emitter`) if it has one, else ``t0 + (L − τ) / (1 + δ)``."""
    clk = a.get("clock")
    return clk.emitter(L) if clk is not None else t0 + (np.asarray(L, float) - a["tau"]) / (1 + a["drift"])


def rate(a, t):
    """dL/dt of array ``a`` at true time t (1 + δ without faults): its samples' true-time rate is fs × this."""
    clk = a.get("clock")
    return float(clk.rate(t)) if clk is not None else 1.0 + a["drift"]


def records(sc, faults):
    """{array name: clock record} of a normalised scenario's faulty clocks (truth/clocks.json)."""
    t = np.asarray(sc["t_emit"], float)
    return {a["name"]: clock_record(a["clock"], (faults or {}).get(a["name"]), t - t[0]) for a in sc["arrays"]
            if a.get("clock") is not None}


# ----------------------------------------------------------------------------------------------- not a clock
def doubt_arrivals(features, array, events, flag="nlos"):
    """A copy of (featsim) ``features`` with ``array``'s arrivals at ``events`` flagged ``flag`` (the frontend's
    doubt, docs/frontend.md): what the range track does with the events on one side of a large clock step, whose
    arrivals all sit one size off its track (a drop: those before it read as late, reflection-like). Its TDOA-M
    and DOA rows at those events and its TDOA-S rows from or to them get the flag (``+``-joined to any there)."""
    ev = {int(e) for e in events}
    out = dict(features)
    for name in ("tdoa_m", "tdoa_s", "doa"):
        df = features[name].copy()
        at = (df["event"].isin(ev) if "event" in df.columns else df["from_event"].isin(ev) | df["to_event"].isin(ev))
        mine = at.to_numpy() & (df["array"].astype(str).to_numpy() == array)
        old = flag_text(df)
        df["flag"] = np.where(mine, np.where(old == "", flag, old + "+" + flag), old)
        out[name] = df
    return out


def delay_arrivals(features, array, delays):
    """A copy of (featsim) ``features`` with ``array``'s arrivals late by ``delays`` {event: s}: what a blocked
    line of sight does (the first arrival is a reflection, late by a path difference that changes from stop to
    stop), the contrast to a clock step (late by one size at every later event). Its TDOA-M at event j gain
    delays[j], its TDOA-S over (a, b) gain delays[b] − delays[a]; the reference's delays shift every TDOA-M."""
    d = {int(k): float(v) for k, v in delays.items()}
    ref = features["meta"]["reference_array"]
    out = dict(features)
    tm = features["tdoa_m"].copy()
    late = tm["event"].map(lambda e: d.get(int(e), 0.0)).to_numpy(float)
    sign = np.where(tm["array"].to_numpy() == array, 1.0, 0.0) - (1.0 if array == ref else 0.0)
    tm["tdoa"] = tm["tdoa"].to_numpy(float) + sign * late
    ts = features["tdoa_s"].copy()
    mine = ts["array"].to_numpy() == array
    step = (ts["to_event"].map(lambda e: d.get(int(e), 0.0)) - ts["from_event"].map(lambda e: d.get(int(e), 0.0))).to_numpy(float)
    ts["tdoa"] = ts["tdoa"].to_numpy(float) + np.where(mine, step, 0.0)
    out["tdoa_m"], out["tdoa_s"] = tm, ts
    return out
