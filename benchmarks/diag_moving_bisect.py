"""Why an array of a moving session ends far off while its stopped twin does not (issue 27): each suspect
cause replaced by its truth in turn, one calibration each, against the simulator's own scene.

    python benchmarks/bench_deploy.py --only moving:350,351 --work /tmp/dep     # renders + `calib run`
    python benchmarks/diag_moving_bisect.py --seeds 350,351 --work /tmp/dep

Per seed of the ``moving`` preset: the session under ``--work`` (``moving_SEED``, as bench_deploy renders it;
rendered here when absent), its features (``runs/moving_SEED/features`` of bench_deploy's `calib run`, else
extracted here as `calib run` does, re-timing pass included) and its stopped twin (the same scene with the
speaker held at each sweep start, diag_moving_arrivals.py's ``static`` variant, rendered under ``--work``).
Every calibration is the library's ``calibrate`` with `calib run`'s options; truth is the scenario
(:func:`calib.pipeline.simulate.roomsim.make_scenario`).

Rows replaced by truth (the estimator's own row model at the true scene):

    true DOA     every DOA: the direction from the array to the source doa_time_s into the sweep (true path)
    true TDOA    TDOA-M / TDOA-S from the arrivals the estimator models (sweep start + β ṙ(t*)/c + β drift)
                 with the TRUE trajectory's range rate: what is left is only the velocity the estimator takes
                 from events.csv/odometry (its Hermite curve at t*)
    no vel. err  the measured TDOAs with the velocity error removed (the difference between the shift at the
                 true range rate and the shift the estimator computes at the true geometry from the odometry)

Columns: the worst array (largest position error of the baseline) and its error ± stated std (cm) as `calib run`
solves it, with the joint solve started at the true state (a wrong starting basin shows here), under each
substitution, and the array whose DOAs alone, replaced by the truth, bring it closest (its error then, cm); the stated sigma_tdoa (µs) and the part of it the frontend adds for the motion (``motion_sd``);
at the true state: the TDOA residual RMS (µs) with the measured rows, the velocity error's share per arrival
(RMS, µs) and the worst array's own arrival error (TDOA-S RMS with the velocity error removed, µs); the worst
array's DOA error RMS (deg) in the moving session and in its stopped twin; the stopped twin's calibration;
the Cramér–Rao bound of the worst array's position (cm) at the stated sigma_tdoa and at the sigma without the
motion part.
"""
from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
import diag_moving_arrivals as dma  # noqa: E402  (a sibling script: its stopped twin and seed parser)

T_GRID = 501   # samples of the range over the sweep


def features_of(seed, work):
    """(validated scenario, features, truth frames) of ``moving_SEED`` under ``work``."""
    from calib.pipeline.formats.io import read_features, read_truth
    from calib.pipeline.simulate.roomsim import make_scenario, simulate
    from calib.pipeline.simulate.scenario import validate_scenario

    folder = work / f"moving_{seed}"
    sc = make_scenario("moving", seed)
    if not (folder / "session.toml").exists():
        simulate(sc, folder)
    run = work / "runs" / f"moving_{seed}" / "features"
    if (run / "meta.json").exists():
        feats = read_features(run)
    else:
        cache = folder.parent / f"moving_{seed}.features.pkl"
        if not cache.exists():
            from calib.pipeline.features import session_features
            cache.write_bytes(pickle.dumps(session_features(folder)[0]))
        feats = pickle.loads(cache.read_bytes())
    return validate_scenario(sc), feats, read_truth(folder / "truth")


def _centre(a):
    return np.asarray(a["position"]) + np.asarray(a["R"]) @ np.mean(np.asarray(a["mics"], float), axis=0)


def true_arrivals(vs, meta):
    """({(array, event index): modelled arrival with the true trajectory}, {…: its shift β ṙ(t*)/c})."""
    c, beta, ts = meta["speed_of_sound"], meta["chirp_drift_bias"], meta.get("stretch_time_s") or 0.0
    traj, t_emit = vs["trajectory"], np.asarray(vs["t_emit"], float)
    tau = np.linspace(0.0, vs["chirp"]["duration"], T_GRID)
    arrival, shift = {}, {}
    for a in vs["arrays"]:
        x = _centre(a)
        for j in range(len(t_emit)):
            rng = np.linalg.norm(traj(t_emit[j] + tau) - x, axis=1) / c
            start = (1 + a["drift"]) * (t_emit[j] + rng[0] - t_emit[0]) + a["tau"] + beta * a["drift"]
            shift[(a["name"], j)] = beta * np.interp(ts, tau, np.gradient(rng, tau))
            arrival[(a["name"], j)] = start + shift[(a["name"], j)]
    return arrival, shift


def estimator_shifts(feats, truth):
    """{(array, event index): the shift the estimator removes at the TRUE state, from the features' velocities}."""
    from calib.estimator import rebuild
    from calib.estimator.motion import arrival_shifts, source_velocities, sweep_middle

    m = rebuild(feats, {"arrays": truth["arrays"], "sources": truth["sources"], "report": {}})
    p, st = m["problem"], m["state"]
    vel, _ = source_velocities(feats["events"], p.t, p.odom)
    sh = arrival_shifts(p, st, vel, None, sweep_middle(p.t, p.odom, vel, float(feats["meta"]["stretch_time_s"])))
    return {(str(n), j): sh[i, j] for i, n in enumerate(p.names) for j in range(p.K)}


def true_doas(vs, t_doa):
    traj, t_emit = vs["trajectory"], np.asarray(vs["t_emit"], float)
    out = {}
    for a in vs["arrays"]:
        u = (traj(t_emit + t_doa) if traj is not None else np.asarray(vs["sources"], float)) - _centre(a)
        u = u @ np.asarray(a["R"])
        for j, uj in enumerate(u / np.linalg.norm(u, axis=1, keepdims=True)):
            out[(a["name"], j)] = uj
    return out


def replaced(feats, *, tdoa=None, doa=None):
    """Features with TDOA arrivals given per (array, event index) by ``tdoa`` (a function of the row's
    measured value, array and event indices → new value) and DOAs by ``doa`` ({(array, event index): u})."""
    from calib.records import Features

    d = {k: (v.copy() if isinstance(v, pd.DataFrame) else v) for k, v in feats.to_dict().items()}
    ev = {e: j for j, e in enumerate(d["events"]["event"])}
    ref = d["meta"]["reference_array"]
    if tdoa is not None:
        d["tdoa_m"]["tdoa"] = [tdoa(r.tdoa, (r.array, ev[r.event]), (ref, ev[r.event]))
                               for r in d["tdoa_m"].itertuples()]
        d["tdoa_s"]["tdoa"] = [tdoa(r.tdoa, (r.array, ev[r.to_event]), (r.array, ev[r.from_event]))
                               for r in d["tdoa_s"].itertuples()]
    if doa is not None:
        d["doa"][["ux", "uy", "uz"]] = np.array([doa[(r.array, ev[r.event])] for r in d["doa"].itertuples()])
    return Features.from_dict(d)


def calibrate(feats, truth, from_truth=False):
    """{array: (position error m, stated position std m)} of `calib run`'s estimate (reference left out);
    ``from_truth``: the joint solve started at the true state instead of the initialisation's."""
    from calib.estimator import calibrate as cal
    from calib.estimator.problem import build_problem
    from calib.estimator.uncertainty import state_from_frames
    from calib.pipeline.run import estimate_defaults

    o = estimate_defaults()
    loss = o.pop("loss", "cauchy")
    if from_truth:
        o["init_state"] = state_from_frames(build_problem(feats), truth["arrays"], truth["sources"])
    arr = cal(feats, loss=None if loss == "linear" else loss, **o).arrays.set_index("array")
    tru = truth["arrays"].set_index("array")
    xyz, std = ["x", "y", "z"], ["x_std", "y_std", "z_std"]
    return {a: (float(np.linalg.norm(arr.loc[a, xyz].to_numpy(float) - tru.loc[a, xyz].to_numpy(float))),
                float(np.linalg.norm(arr.loc[a, std].to_numpy(float))))
            for a in tru.index if a != feats["meta"]["reference_array"]}


def one_array_doas(feats, truth, vs, worst):
    """'ARRAY: cm' for the array whose DOAs alone, replaced by the truth, bring ``worst`` closest."""
    u = true_doas(vs, feats["meta"]["doa_time_s"])
    best = {}
    for a in feats["meta"]["arrays"]:
        own = {k: v for k, v in u.items() if k[0] == a}
        ev = {e: j for j, e in enumerate(feats["events"]["event"])}
        mixed = {(r.array, ev[r.event]): own.get((r.array, ev[r.event]), np.array([r.ux, r.uy, r.uz]))
                 for r in feats["doa"].itertuples()}
        best[a] = calibrate(replaced(feats, doa=mixed), truth)[worst][0]
    a = min(best, key=best.get)
    return f"{a}: {100 * best[a]:.1f}"


def residual_rms(feats, truth, arrays=None):
    """RMS (µs) of the TDOA-M and TDOA-S residuals at the true state after the estimator's motion correction;
    with ``arrays``: {array: TDOA-S RMS} instead."""
    from calib.estimator import rebuild
    from calib.estimator.factors import evaluate, natural
    from calib.estimator.motion import corrected, source_velocities

    m = rebuild(feats, {"arrays": truth["arrays"], "sources": truth["sources"], "report": {}})
    p, st, meta = m["problem"], m["state"], feats["meta"]
    vel, _ = source_velocities(feats["events"], p.t, p.odom)
    pc = corrected(p, st, vel, None, float(meta.get("doa_time_s") or 0.0), meta.get("stretch_time_s"))
    res = {f.kind: 1e6 * natural(f) for f in evaluate(pc, st, m["layout"], ["tdoa_m", "tdoa_s"])}
    rms = lambda v: float(np.sqrt(np.mean(np.square(v)))) if len(v) else float("nan")
    if arrays:
        return {a: rms(res["tdoa_s"][np.asarray(p.names)[p.tdoa_s.arr] == a]) for a in arrays}
    return rms(np.r_[res["tdoa_m"], res["tdoa_s"]])


def doa_error(feats, vs, array, t_doa):
    """RMS angle (deg) between the DOAs of ``array`` and the true directions ``t_doa`` into the sweep."""
    u = true_doas(vs, t_doa)
    ev = {e: j for j, e in enumerate(feats["events"]["event"])}
    d = feats["doa"][feats["doa"]["array"] == array]
    dots = [np.dot([r.ux, r.uy, r.uz], u[(array, ev[r.event])]) for r in d.itertuples()]
    return float(np.sqrt(np.mean(np.degrees(np.arccos(np.clip(dots, -1, 1))) ** 2)))


def bound(feats, truth, array, sigma):
    """CRLB (cm) of ``array``'s position with meta sigma_tdoa = ``sigma``."""
    from calib.estimator import crlb
    from calib.records import Features

    f = Features.from_dict({**feats.to_dict(), "meta": {**feats["meta"], "sigma_tdoa": float(sigma)}})
    b = crlb(f, truth)
    i = list(b["problem"].names).index(array)
    return 100 * float(np.linalg.norm(b["std"]["x"][i]))


def one_seed(seed, work):
    from calib.frontend.extract import MOTION_MODEL_ERROR_RETIMED, motion_sd

    vs, feats, truth = features_of(seed, work)
    meta = feats["meta"]
    base = calibrate(feats, truth)
    worst = max(base, key=lambda a: base[a][0])
    true_arr, true_sh = true_arrivals(vs, meta)
    est_sh = estimator_shifts(feats, truth)
    vel_err = {k: true_sh[k] - est_sh[k] for k in true_sh}
    no_vel = replaced(feats, tdoa=lambda z, k, k0: z - vel_err[k] + vel_err[k0])
    subs = {"true DOA": replaced(feats, doa=true_doas(vs, meta["doa_time_s"])),
            "true TDOA": replaced(feats, tdoa=lambda z, k, k0: true_arr[k] - true_arr[k0]),
            "no vel. err": no_vel}
    _, twin, _ = dma.session(seed, "static", work)
    motion = motion_sd(feats["events"], meta["speed_of_sound"], meta["chirp_drift_bias"], MOTION_MODEL_ERROR_RETIMED)
    own = float(np.sqrt(max(meta["sigma_tdoa"] ** 2 - motion ** 2, 0.0)))
    fmt = lambda r: f"{100 * r[worst][0]:.1f} ± {100 * r[worst][1]:.1f}"
    row = {"seed": seed, "worst": worst, "baseline": fmt(base), "started at truth": fmt(calibrate(feats, truth, True))}
    row |= {k: fmt(calibrate(f, truth)) for k, f in subs.items()}
    row["true DOA of one array"] = one_array_doas(feats, truth, vs, worst)
    row |= {"stopped twin": fmt(calibrate(twin, truth)),
            "σ_tdoa (motion) µs": f"{1e6 * meta['sigma_tdoa']:.0f} ({1e6 * motion:.0f})",
            "res. at truth µs": f"{residual_rms(feats, truth):.0f}",
            "vel. err per arrival µs": f"{1e6 * np.sqrt(np.mean(np.square(list(vel_err.values())))):.0f}",
            "worst's own arrivals µs": f"{residual_rms(no_vel, truth, [worst])[worst]:.0f}",
            "worst's DOA err moving / stopped deg": f"{doa_error(feats, vs, worst, meta['doa_time_s']):.2f} / "
                                                    f"{doa_error(twin, vs, worst, 0.0):.2f}",
            "CRLB cm at stated σ / frontend's own σ": f"{bound(feats, truth, worst, meta['sigma_tdoa']):.1f} / "
                                             f"{bound(feats, truth, worst, max(own, 1e-7)):.1f}"}
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="350,351")
    ap.add_argument("--work", type=Path, required=True)
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in dma.parse_seeds(args.seeds):
        t0 = time.perf_counter()
        rows.append(one_seed(seed, args.work))
        print(" | ".join(str(v) for v in rows[-1].values()) + f" | {time.perf_counter() - t0:.0f} s", flush=True)
    df = pd.DataFrame(rows)
    print("| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns))
    for r in df.itertuples(index=False):
        print("| " + " | ".join(str(v) for v in r) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
