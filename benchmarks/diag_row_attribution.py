"""Which rows put an array where it ended (issue 27): each array's position error against the simulator's truth,
split linearly over the feature rows that the estimator's final solve used.

    python benchmarks/diag_row_attribution.py SESSION RUN                # SESSION: `calib simulate` output
    python benchmarks/diag_row_attribution.py SESSION RUN --rows A5      # RUN: its `calib run` output

The features of RUN are calibrated again in-process (``calibrate``, as `calib run` does), and at θ0 = the true
array poses, clocks and sources (the solve's own nuisances: emission corrections, velocity errors, odometry
yaw) the solve's final problem is linearised with its outlier mask: θ̂ − θ0 ≈ −(JᵀWJ)⁺ JᵀW r(θ0). Row k adds
−(JᵀWJ)⁺ J_kᵀ w_k r_k(θ0): its share of every array's error. The linear prediction is printed beside the actual
error (they agree to a few mm where the solve is in the true basin; far apart means another basin). Rows are
grouped by kind, array and the truth's line of sight of their arrival(s) (truth/los.csv: ``clr`` line of
sight, ``wall`` blocked, ``att`` direct path attenuated by an obstacle or the mount); ``--rows ARRAY`` lists
the single rows that move ARRAY most, with their whitened residual at the truth (``r0``) and at the estimate
(``re``): a row far off at the truth but fitted at the estimate is one its event's source (or its own array)
absorbed.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd


def _los_class(t, los):
    """(rows,) 'clr' / 'wall' / 'att' of each row of a feature table (the worst of a TDOA-S row's two events)."""
    evs = [t["event"].to_numpy(int)] if "event" in t else [t["from_event"].to_numpy(int), t["to_event"].to_numpy(int)]
    arr = t["array"].to_numpy()
    ok = np.min([los["los"].reindex(list(zip(e, arr))).fillna(1).to_numpy(int) for e in evs], axis=0)
    wall = np.any([los["cause"].reindex(list(zip(e, arr))).astype(str).str.contains("wall").to_numpy()
                   for e in evs], axis=0)
    return np.where(wall, "wall", np.where(ok == 0, "att", "clr"))


def attribution(session, run):
    """(rows DataFrame: kind, array, event(s), los class, flag, used, r0, re; contributions (n_params, rows) m;
    problem, layout, estimate, truth state)."""
    from calib.estimator import calibrate
    from calib.estimator.assess import outlier_mask
    from calib.estimator.factors import active_kinds
    from calib.estimator.problem import make_layout
    from calib.estimator.solver import linearise
    from calib.estimator.uncertainty import state_from_frames
    from calib.pipeline.formats.io import read_features, read_truth

    feat = read_features(Path(run) / "features")
    truth = read_truth(Path(session) / "truth")
    los = pd.read_csv(Path(session) / "truth" / "los.csv", keep_default_na=False).set_index(["event", "array"])
    tables = {}
    for k in ("tdoa_m", "tdoa_s", "doa"):
        t = feat[k].copy()
        t["csv_line"] = np.arange(len(t)) + 2
        tables[k] = t
    res = calibrate(feat.replace(**tables))
    p, st = res.problem, res.state
    kinds, lay = active_kinds(p), make_layout(p)
    mask = outlier_mask(p, st, lay, kinds, res.report.get("outliers"))
    st0, tr = st.copy(), state_from_frames(p, truth["arrays"], truth["sources"])
    for f in ("x", "R", "offset", "drift", "s"):
        setattr(st0, f, getattr(tr, f))
    lin = linearise(p, st0, lay, kinds, mask=mask, dense=True)
    J, w = np.asarray(lin.J), (lin.w > 0).astype(float)
    contrib = -(np.linalg.pinv(J.T @ (J * w[:, None])) @ (J * w[:, None]).T) * lin.r[None, :]
    rows = []
    for f in lin.factors:
        src = {"cone": "doa"}.get(f.kind, f.kind)
        if src in tables:
            t = tables[src].set_index("csv_line").loc[f.row]
            ev = t["event"].astype(str) if "event" in t else t["from_event"].astype(str) + "-" + t["to_event"].astype(str)
            rows.append(pd.DataFrame({"kind": f.kind, "array": t["array"].to_numpy(), "event": ev.to_numpy(),
                                      "los": _los_class(t, los), "flag": t["flag"].astype(str).to_numpy()}))
        else:
            rows.append(pd.DataFrame({"kind": [f.kind] * len(f.r), "array": "-", "event": "", "los": "-", "flag": ""}))
    df = pd.concat(rows, ignore_index=True)
    df["used"] = w > 0
    df["r0"], df["re"] = lin.r, linearise(p, st, lay, kinds, mask=mask, dense=True).r
    return df, contrib, p, lay, st, tr, res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--rows", help="list the single rows that move this array most")
    ap.add_argument("--min-cm", type=float, default=0.5, help="groups moving an array less than this are not shown")
    args = ap.parse_args(argv)
    df, contrib, p, lay, st, tr, res = attribution(args.session, args.run)
    los = pd.read_csv(args.session / "truth" / "los.csv")
    clear = {a for a, f in los.groupby("array")["los"].mean().items() if f > 0.5}
    print(f"{args.session.name}: reference {p.names[p.ref]}, verdict {res.report['verdict']['status']}, "
          f"unreliable {res.report.get('unreliable_arrays')}; * = line of sight in most events")
    used = df[df.used]
    for i, name in enumerate(map(str, p.names)):
        cols = lay.x[i]
        if np.any(cols < 0):
            continue
        err, pred = 100 * (st.x[i] - tr.x[i]), 100 * contrib[cols].sum(1)
        print(f"\n{name}{'*' if name in clear else ''}: error {np.linalg.norm(err):.1f} cm {np.round(err, 1)}, "
              f"linear {np.linalg.norm(pred):.1f} cm {np.round(pred, 1)}")
        d = used.assign(**dict(zip(("dx", "dy", "dz"), 100 * contrib[cols][:, used.index])))
        g = d.groupby(["kind", "array", "los"])[["dx", "dy", "dz"]].sum()
        g["cm"], g["rows"] = np.linalg.norm(g.to_numpy(), axis=1), d.groupby(["kind", "array", "los"]).size()
        print(g[g.cm >= args.min_cm].sort_values("cm", ascending=False).round(1).to_string())
        if args.rows == name:
            d["cm"] = np.linalg.norm(d[["dx", "dy", "dz"]].to_numpy(), axis=1)
            print(d.sort_values("cm", ascending=False).head(15).round(2).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
