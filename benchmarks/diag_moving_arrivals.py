"""What a moving source's corrected arrivals still miss (issue 27): each arrival against the simulator's exact path.

    python benchmarks/diag_moving_arrivals.py --seeds 400-402 --work /tmp/diag
    python benchmarks/diag_moving_arrivals.py --seeds 410-413 --variants default anechoic static --work DIR

Per seed of the ``moving`` preset and variant (``default``: the preset as `calib simulate` renders it;
``anechoic``: RT60 0 and no noise; ``static``: the stopped twin, the same scene with the speaker held at
each sweep start; ``static-own``: the stopped twin timed with each event's own carrier phase, as the
frontend times a moving source's arrivals, ``timing.locate`` ``own_phase``), the frontend runs as `calib features` does (re-timing pass included) and every arrival
(diagnostics, on its array's clock) is compared with the truth of the scenario's own trajectory spline:

    start      the sweep start's arrival at the array's mic centroid (retarded time), on its clock
    t* model   start + β (ṙ(t*)/c + drift)             what the estimator models (here with the TRUE velocity)
    cubic      start + β (a1 + drift) + 2 β t* a2 + 6 γ3 a3

a_k: the coefficients of the range over the sweep, (r(t) − r(0))/c ≈ a1 t + a2 t² + a3 t³ (least squares on
[0, T]); β, t* from meta (``chirp_drift_bias``, ``stretch_time_s``) and γ3 measured on the template as they
are (:func:`calib.frontend.timing.delay_shift` with the delay ± j t³/6). The t* model is exact for a range
that is quadratic over the sweep; its cubic coefficient is β t*²/2 where the estimator's is γ3, so a range
jerk r⃛ leaves (γ3 − β t*²/2) r⃛ / c. Columns: RMS over the unflagged arrivals after each array's median is
removed (a constant per array is a clock offset to the estimator), the largest, the RMS range jerk (m/s³,
6 a3 c) and the correlation of the t* model's residual with (γ3 − β t*²/2) r⃛ / c; per array the cubic
model's RMS.
"""
from __future__ import annotations

import argparse
import contextlib
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

T_GRID = 501   # samples of the range over the sweep for its cubic fit


def parse_seeds(spec):
    out = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def scenario(seed, variant):
    from calib.pipeline.simulate.roomsim import make_scenario

    over = {"rt60": 0.0, "snr": float("inf")} if variant == "anechoic" else {}
    sc = make_scenario("moving", seed, **over)
    if variant.startswith("static"):   # the sources are the trajectory's positions at the sweep starts already
        sc = {k: v for k, v in sc.items() if k != "trajectory"}
    return sc


def session(seed, variant, work):
    """(validated scenario, features, diagnostics), rendered and extracted once per --work folder."""
    from calib.pipeline.features import session_features
    from calib.pipeline.simulate.roomsim import simulate
    from calib.pipeline.simulate.scenario import validate_scenario

    sc = scenario(seed, variant)
    folder = work / f"moving_{seed}_{variant}"
    twin = work / f"moving_{seed}_static"
    if variant == "static-own" and (twin / "session.toml").exists() and not folder.exists():
        folder.mkdir()   # the same recordings as the stopped twin's
        for f in twin.iterdir():
            if f.name != "features.pkl":
                (folder / f.name).symlink_to(f.resolve())
    if not (folder / "session.toml").exists():
        simulate(sc, folder)
    cache = folder / "features.pkl"
    if cache.exists():
        feats, diag = pickle.loads(cache.read_bytes())
    else:
        with own_phase(variant == "static-own"):
            feats, diag = session_features(folder)
        diag = {k: diag[k] for k in ("arrays", "event_ids")}
        cache.write_bytes(pickle.dumps((feats, diag)))
    return validate_scenario(sc), feats, diag


@contextlib.contextmanager
def own_phase(on):
    """Every event timed with its own carrier phase (``timing.locate``'s ``own_phase``) while ``on``."""
    from calib.frontend import timing

    inner = timing._carrier_phase
    if on:
        timing._carrier_phase = lambda z, phase, own: inner(z, phase, True)
    try:
        yield
    finally:
        timing._carrier_phase = inner


def cubic_moment(folder, ref):
    """γ3 (s³): this estimator's arrival shift per unit j of a received delay j t³ / 6, at the reference's
    rate and timing settings (as β and t*)."""
    from calib.frontend import DEFAULTS
    from calib.frontend.extract import _timing_layout, chirp_band, chirp_template, read_header
    from calib.frontend.timing import delay_shift
    from calib.pipeline.formats.session import read_session

    s = read_session(folder)
    a = next(x for x in s["arrays"] if x["name"] == ref)
    fs = int(read_header(a).samplerate)
    tpl = chirp_template(s["chirp"], fs)
    band = chirp_band(s["chirp"], tpl, fs)
    g = _timing_layout(np.asarray(a["mics"], float), band, fs, s["speed_of_sound"], len(tpl), DEFAULTS)
    j = 0.5 / ((band[1] - band[0]) * 1.5 * (len(tpl) / fs) ** 3)   # a quarter pulse of group-delay spread
    s1, s2 = (delay_shift(tpl, fs, band, g["locate_kw"], g["pre"], g["seg_len"], DEFAULTS["whiten_hz"],
                          lambda t, q=q: q * t ** 3 / 6) for q in (j, -j))
    return (s1 - s2) / (2 * j)


def arrival_table(vs, feats, diag, gamma3):
    """One row per (array, event): measured arrival, both models, the range jerk."""
    meta = feats["meta"]
    c, beta = meta["speed_of_sound"], meta["chirp_drift_bias"]
    ts = meta.get("stretch_time_s") or 0.0
    traj, t_emit = vs["trajectory"], np.asarray(vs["t_emit"], float)
    dur = vs["chirp"]["duration"]
    tau = np.linspace(0.0, dur, T_GRID)
    src = np.asarray(vs["sources"], float)
    rows = []
    for a in vs["arrays"]:
        x = np.asarray(a["position"]) + np.asarray(a["R"]) @ np.mean(np.asarray(a["mics"], float), axis=0)
        for r in diag["arrays"][a["name"]]["arrivals"]:
            j = diag["event_ids"].index(r["event"])
            path = traj(t_emit[j] + tau) if traj is not None else np.repeat(src[j][None], len(tau), 0)
            rng = np.linalg.norm(path - x, axis=1) / c
            a3, a2, a1, _ = np.polyfit(tau, rng - rng[0], 3)
            start = (1 + a["drift"]) * (t_emit[j] + rng[0] - t_emit[0]) + a["tau"] + beta * a["drift"]
            rdot_ts = np.interp(ts, tau, np.gradient(rng, tau))
            rows.append({"array": a["name"], "event": r["event"], "flag": r["flag"], "res_tstar":
                         r["time"] - (start + beta * rdot_ts), "res_cubic": r["time"] - (
                             start + beta * a1 + 2 * beta * ts * a2 + 6 * gamma3 * a3),
                         "jerk": 6 * a3 * c, "pred": (gamma3 - beta * ts ** 2 / 2) * 6 * a3})
    return pd.DataFrame(rows)


def summary(df):
    d = df[df["flag"] == ""].copy()
    for k in ("res_tstar", "res_cubic"):
        d[k] = 1e6 * (d[k] - d.groupby("array")[k].transform("median"))
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))
    per = d.groupby("array")["res_cubic"].apply(rms)
    corr = np.corrcoef(d["res_tstar"], d["pred"])[0, 1] if d["pred"].std() > 0 else float("nan")
    return {"rows": len(d), "of": len(df), "jerk_rms": rms(df["jerk"]), "tstar_rms_us": rms(d["res_tstar"]),
            "tstar_max_us": float(np.max(np.abs(d["res_tstar"]))), "cubic_rms_us": rms(d["res_cubic"]),
            "cubic_max_us": float(np.max(np.abs(d["res_cubic"]))), "corr_jerk": float(corr),
            "per_array_cubic_us": " ".join(f"{n} {v:.1f}" for n, v in per.items())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="400-402")
    ap.add_argument("--variants", nargs="+", default=["default", "anechoic"],
                    choices=["default", "anechoic", "static", "static-own"])
    ap.add_argument("--work", type=Path, required=True)
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    out = []
    for seed in parse_seeds(args.seeds):
        for variant in args.variants:
            t0 = time.perf_counter()
            vs, feats, diag = session(seed, variant, args.work)
            g3 = cubic_moment(args.work / f"moving_{seed}_{variant}", feats["meta"]["reference_array"])
            s = {"session": f"moving {seed} {variant}", "gamma3": g3,
                 **summary(arrival_table(vs, feats, diag, g3)), "s": time.perf_counter() - t0}
            out.append(s)
            print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in s.values()), flush=True)
    df = pd.DataFrame(out)
    print(df.drop(columns=["gamma3", "s"]).round(2).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
