"""How wrong are the arrivals the frontend doubts, and how much do their blunders move the arrays (issue 27)?

    python benchmarks/diag_flagged_rows.py WORK deploy_505 deploy_506 ...     # WORK: bench_deploy.py's --work
    python benchmarks/diag_flagged_rows.py WORK office_505 --blunder-us 100 --no-oracle

For each session (``WORK/NAME``: `calib simulate` output; ``WORK/runs/NAME``: its `calib run`) the final solve's
TDOA rows are taken at the truth (``diag_row_attribution.attribution``: true poses, clocks and sources, the solve's
own nuisances) and their errors split into one error per arrival (array, event) by least squares (a TDOA-S row
is the difference of an array's two arrivals, a TDOA-M row of an array's and the reference's; each array's
median is taken out: its clock offset absorbs a constant). Each arrival then carries its frontend flag, quality
and lateness (diagnostics.json) and the truth's line of sight (truth/los.csv).

Printed: (1) per doubt kind (``nlos`` rows are screened out before the solve, so absent; ``mic_spread`` before
``weak_direct`` before any other timing doubt; ``-`` none) the arrivals' true error: RMS, median, 90th percentile,
the share beyond ``--blunder-us`` and beyond 200 µs, and beyond 5× the arrival's whitening sigma (its array's
median TDOA-S row sigma in the solve, / √2); (2) per array more than ``--min-cm`` off, the part of its error (along it, linear:
``diag_row_attribution``) that the rows of blunder arrivals carry, flagged and unflagged, and (unless
``--no-oracle``) its error when every such row is taken out of the features before calibrating (an oracle: the
most any treatment of blunders could give; the linear share is not that, the other rows and the outlier tests
rebalance).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.sparse as sp
import scipy.sparse.linalg as spl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_row_attribution import attribution  # noqa: E402

from calib.frontend.extract import TIMING_DOUBTS

KIND_ORDER = ("nlos", "mic_spread", "weak_direct")   # an arrival's doubt kind: the first of these it has
FAR_SIGMA = 5.0        # "beyond 5× its sigma": the estimator's outlier level (outlier_threshold)


def doubt_kind(flag):
    """'nlos' / 'mic_spread' / 'weak_direct' (the first of KIND_ORDER the flag holds), 'other' (another timing
    doubt), '-' (none)."""
    parts = [x for x in str(flag or "").split("+") if x in TIMING_DOUBTS]
    return next((k for k in KIND_ORDER if k in parts), "other" if parts else "-")


def arrival_errors(rows, ref):
    """(arrivals DataFrame: array, event, err_us, sig_us) from the TDOA rows at the truth (``rows``:
    attribution's, with ``err`` (s) and ``sigma`` (s)): least squares, each array's median taken out."""
    t = rows[rows.kind.isin(["tdoa_m", "tdoa_s"])].reset_index(drop=True)
    keys, ri, ci, v = {}, [], [], []
    for n, (kind, arr, ev) in enumerate(zip(t.kind, t["array"], t.event)):
        a, b = ((arr, ev), (ref, ev)) if kind == "tdoa_m" else ((arr, ev.split("-")[1]), (arr, ev.split("-")[0]))
        for key, sign in ((a, 1.0), (b, -1.0)):
            ri.append(n)
            ci.append(keys.setdefault((key[0], int(key[1])), len(keys)))
            v.append(sign)
    A = sp.csr_matrix((v, (ri, ci)), shape=(len(t), len(keys)))
    e = spl.lsqr(A, t.err.to_numpy(), atol=1e-14, btol=1e-14)[0]
    out = pd.DataFrame([(a, ev, 1e6 * e[i]) for (a, ev), i in keys.items()], columns=["array", "event", "err_us"])
    out["err_us"] -= out.groupby("array")["err_us"].transform("median")
    sig = t[t.kind == "tdoa_s"].groupby("array")["sigma"].median() / np.sqrt(2)
    out["sig_us"] = 1e6 * out["array"].map(sig)
    return out


def session_arrivals(work, name):
    """(arrivals with flags, quality, lateness, line of sight; attribution rows with ``err``; contributions;
    problem; layout; estimate; truth) of one session."""
    session, run = work / name, work / "runs" / name
    df, contrib, p, lay, st, tr, res = attribution(session, run)
    from calib.estimator.factors import active_kinds
    from calib.estimator.solver import linearise
    lin = linearise(p, st, lay, active_kinds(p), dense=True)
    df["sigma"] = np.concatenate([np.broadcast_to(f.row_sigma, len(f.r)) for f in lin.factors])
    df["err"] = df["r0"] * df["sigma"]          # model − measured at the truth (s): > 0 an early arrival
    arr = arrival_errors(df, str(p.names[p.ref]))
    diag = json.loads((run / "diagnostics" / "diagnostics.json").read_text())
    recs = [{"array": n, "event": int(r["event"]), "quality": r.get("quality"), "flag": r.get("flag") or "",
             "late_us": 1e6 * r["late_s"] if r.get("late_s") is not None else np.nan,
             "sd_us": 1e6 * (r.get("sd_s") or np.nan), "doa_sd_deg": r.get("doa_sd_deg")}
            for n, a in diag["arrays"].items() for r in a.get("arrivals") or []]
    los = pd.read_csv(session / "truth" / "los.csv", keep_default_na=False)[["event", "array", "los",
                                                                             "direct_minus_reflection_db"]]
    arr = arr.merge(pd.DataFrame(recs), on=["array", "event"], how="left").merge(los, on=["array", "event"], how="left")
    arr["kind"] = arr.flag.map(doubt_kind)
    arr["session"] = name
    return arr, df, contrib, p, lay, st, tr


def kind_table(arr, blunder_us):
    """Per doubt kind: the arrivals' true error statistics (µs) and blunder shares."""
    a = arr.assign(abs=arr.err_us.abs(), far=arr.err_us.abs() > FAR_SIGMA * arr.sig_us)
    g = a.groupby("kind").agg(n=("abs", "size"), rms=("err_us", lambda x: np.sqrt(np.mean(x**2))),
                              median=("abs", "median"), p90=("abs", lambda x: np.quantile(x, 0.9)),
                              blunder=("abs", lambda x: np.mean(x > blunder_us)),
                              over_200=("abs", lambda x: np.mean(x > 200)),
                              over_5sigma=("far", "mean"), row_sigma=("sig_us", "median"), los=("los", "mean"))
    return g.rename(columns={"blunder": f"> {blunder_us:g} µs"})


def blunder_rows(df, arr, ref, blunder_us):
    """(rows,) bool: TDOA rows of the final solve holding an arrival more than ``blunder_us`` off; (rows,) bool:
    those rows flagged; the set of blunder arrivals {(array, event)}."""
    far = arr[arr.err_us.abs() > blunder_us]
    big = set(zip(far["array"], far.event.astype(int)))
    hit = np.zeros(len(df), bool)
    for n, (kind, a, ev) in enumerate(zip(df.kind, df["array"], df.event)):
        if kind == "tdoa_m":
            hit[n] = (a, int(ev)) in big or (ref, int(ev)) in big
        elif kind == "tdoa_s":
            x, y = ev.split("-")
            hit[n] = (a, int(x)) in big or (a, int(y)) in big
    return hit, df.flag.ne("").to_numpy(), big


def oracle_errors(work, name, big, ref):
    """{array: position error (cm)} of a calibration of the session's features without the TDOA rows of the
    arrivals ``big`` (every row holding one; the reference's: its event's TDOA-M rows)."""
    from calib.estimator import calibrate
    from calib.pipeline.formats.io import read_features
    feat = read_features(work / "runs" / name / "features")
    m, t = feat["tdoa_m"], feat["tdoa_s"]
    m = m[[not ((a, e) in big or (ref, e) in big) for a, e in zip(m["array"], m.event)]]
    t = t[[not ((a, x) in big or (a, y) in big) for a, x, y in zip(t["array"], t.from_event, t.to_event)]]
    est = calibrate(feat.replace(tdoa_m=m, tdoa_s=t))["arrays"].set_index("array")
    tru = pd.read_csv(work / name / "truth" / "arrays.csv").set_index("array")
    d = est[["x", "y", "z"]].to_numpy(float) - tru.loc[est.index, ["x", "y", "z"]].to_numpy(float)
    return dict(zip(est.index, 100 * np.linalg.norm(d, axis=1)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("sessions", nargs="+")
    ap.add_argument("--blunder-us", type=float, default=150.0, help="an arrival this far off is a blunder")
    ap.add_argument("--min-cm", type=float, default=3.0, help="arrays less off than this are not listed")
    ap.add_argument("--no-oracle", action="store_true", help="skip the calibrations without the blunders' rows")
    args = ap.parse_args(argv)
    pd.set_option("display.width", 200)
    every = []
    for name in args.sessions:
        arr, df, contrib, p, lay, st, tr = session_arrivals(args.work, name)
        every.append(arr)
        ref = str(p.names[p.ref])
        hit, flagged, big = blunder_rows(df, arr, ref, args.blunder_us)
        oracle = None if args.no_oracle else oracle_errors(args.work, name, big, ref)
        used = df.used.to_numpy()
        for i, a in enumerate(map(str, p.names)):
            cols = lay.x[i]
            err = 100 * (st.x[i] - tr.x[i])
            if np.any(cols < 0) or np.linalg.norm(err) < args.min_cm:
                continue
            c = 100 * contrib[cols]
            along = (lambda m: float(c[:, m & used].sum(1) @ err / np.linalg.norm(err)))
            print(f"{name} {a}: {np.linalg.norm(err):.1f} cm; along it, blunder rows flagged "
                  f"{along(hit & flagged):+.1f} "
                  f"({int((hit & flagged & used).sum())} rows), unflagged {along(hit & ~flagged):+.1f} "
                  f"({int((hit & ~flagged & used).sum())}); without them (oracle) "
                  f"{'-' if oracle is None else f'{oracle.get(a, np.nan):.1f} cm'}", flush=True)
    print()
    print(kind_table(pd.concat(every, ignore_index=True), args.blunder_us).round(2).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
