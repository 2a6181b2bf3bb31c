"""What makes each array's position std, and do those sources err that much (issue 27's over-naming)?

    python benchmarks/diag_std_sources.py WORK SESSION...   # WORK/SESSION: `calib simulate`; WORK/runs/SESSION: `calib run`
    python benchmarks/diag_std_sources.py WORK SESSION... --json OUT.json

The honest covariance is H⁻¹ B H⁻¹ with B a sum of GᵀG terms (``uncertainty.sandwich_covariance``): each
array's arrivals (TDOA rows through ``arrival_rows``), its planar DOA rows (``planar_doa_rows``, per array), the
other rows per kind and array with their σ² factors, a moving source's velocity error, each array's shared DOA /
cone rotation. An array's position variance is therefore exactly the sum of ‖G H⁻¹[:, x]‖² over those terms
(:func:`std_parts`; the parts add up to the std's variance, checked). Beside each term's claim, the error its rows
actually make at the simulator's truth (true poses, clocks and sources, the solve's nuisances: −H⁻¹ J_gᵀ r_g(θ0),
``diag_row_attribution``), grouped by row source: the reference's DOA rows (``ref``: its planar, shared and own
terms), the array's own DOA rows (``own``), other arrays' DOA rows, the odometry. The TDOA rows are not compared:
all groups' parts together (``linear``) make the array's error only where the truth's clocks are the solve's
parameters (moving, robot sessions: within ~2 cm); elsewhere (h50n's lshape, office, mixed, lab, hall features) the
truth's TDOA residuals are cm to m off (a clock parameterisation the truth's offset / drift do not match), and only
the direction and odometry groups, whose residuals hold no clock, are read. Printed per array: its std, the
three largest terms' shares, and per group error / √claim; per preset the pooled √(Σ error² / Σ claim) (~1 if
the group's std is its error's, < 1: the std claims more than its rows err) over all arrays and over the
over-named ones (named by the verdict while within bench_deploy's bound: position and full rotation angle; a
linear board's roll, which bench_deploy leaves out, counts here).
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_deploy as BD   # noqa: E402
from diag_shared_rotation import final_linearisation as _final_linearisation   # noqa: E402

from calib.estimator import uncertainty as U
from calib.estimator import variance as V
from calib.estimator.motion import motion_noise
from calib.estimator.solver import linearise
from calib.estimator.verdict import median_error
from calib.pipeline.formats.io import read_truth

DIRECTION_PARTS = ("doa_planar", "shared_doa", "shared_cone", "doa", "cone")


def final_linearisation(features_dir):
    """`diag_shared_rotation.final_linearisation` without the set-up findings (the estimator's own std)."""
    return _final_linearisation(features_dir, findings=False)


def truth_linearisation(work, name, p, st, lay, kinds, res, lin):
    """(r0, J0, truth state): the final solve's kept rows (weight > 0) re-linearised at the simulator's truth
    (arrays, sources; the solved clocks and the rest): the error each row makes at the truth, its Jacobian there."""
    truth = read_truth(work / name / "truth")
    st0, tr = st.copy(), U.state_from_frames(p, truth["arrays"], truth["sources"])
    for f in ("x", "R", "offset", "drift", "s"):
        setattr(st0, f, getattr(tr, f))
    lin0 = linearise(p, st0, lay, kinds, mask=res.mask, dense=True)
    return np.where(lin.w > 0, lin0.r, 0.0), np.asarray(lin0.J), tr


def row_labels(p, lin):
    """(M,) kind and (M,) array name ('-' for rows of no array) of each residual row."""
    kind, arr = [], []
    for f in lin.factors:
        kind += [f.kind] * len(f.r)
        rows = p.rows(f.kind) if f.kind in ("doa", "cone", "tdoa_m", "tdoa_s") else None
        arr += [str(p.names[i]) for i in np.repeat(rows.arr, f.dim)] if rows is not None else ["-"] * len(f.r)
    return np.array(kind), np.array(arr)


def std_parts(p, lin, lay, st, cov, meta, motion):
    """{name: G} with Σ GᵀG the B of the honest covariance (``honest_covariance``'s arguments), and that covariance."""
    vel = U.velocity_rows(lin, lay, motion)
    fac = V.covariance_factors(p, lin, cov, lower=V.LOWERED_KINDS + (U.ARRIVAL_KINDS if vel is not None else ()))
    stated = V.covariance_factors(p, lin, cov)
    shared_arrivals, normals = bool(meta.get("tdoa_shared_arrivals")), U.plane_normals(meta, p.names)
    sdoa, scone = U.shared_doa_rows(p, lin, stated), U.shared_cone_rows(p, lin, st, stated)
    honest = U.sandwich_covariance(p, lin, cov, fac, shared_arrivals, normals, vel, U._sum_shared(sdoa, scone))
    J = lin.J.toarray() if hasattr(lin.J, "toarray") else np.asarray(lin.J)
    kind, arr = row_labels(p, lin)
    own, parts = lin.w > 0, {}
    whole = U.planar_doa_rows(p, lin, normals, fac, cov)
    if whole is not None:
        own &= ~whole["rows"]
        for i in np.flatnonzero(np.any(normals != 0, axis=1)):
            alone = np.where(np.arange(p.N)[:, None] == i, normals, 0.0)
            g = U.planar_doa_rows(p, lin, alone, fac, cov)
            if g is not None:
                parts[f"doa_planar:{p.names[i]}"] = g["G"]
    D = U.arrival_rows(p, lin, fac) if shared_arrivals else None
    if D is not None:
        own &= np.asarray(abs(D).sum(axis=1)).ravel() == 0
        G = np.asarray(D.T @ J)
        for i in range(p.N):
            parts[f"arrival:{p.names[i]}"] = G[i * p.K:(i + 1) * p.K]
    Jf = J * np.sqrt(U.row_factors(p, lin, fac))[:, None]
    for k, a in set(zip(kind[own], arr[own])):
        parts[f"{k}:{a}"] = Jf[own & (kind == k) & (arr == a)]
    if vel is not None:
        parts["velocity:-"] = (J.T @ vel).T
    for name, X in (("shared_doa", sdoa), ("shared_cone", scone)):
        for i in range(p.N) if X is not None else ():
            if np.any(X[:, 3 * i:3 * i + 3]):
                parts[f"{name}:{p.names[i]}"] = (J.T @ X[:, 3 * i:3 * i + 3]).T
    return parts, honest, kind, arr


def group_of(kind, array, name, ref):
    """The row group a row (or a term) of ``kind`` of ``array`` belongs to, seen from array ``name``."""
    if kind in DIRECTION_PARTS:
        return "ref" if array == ref else ("own" if array == name else "other_doa")
    return "tdoa" if kind in ("tdoa_m", "tdoa_s", "arrival", "velocity") else kind


def session(work, name):
    """Per non-reference array: {array, std_cm, err_cm, named, off, parts {term: share}, claim {group: m²},
    error {group: m²}}."""
    cal, res, kinds, stages, meta, lay, lin, cov = final_linearisation(work / "runs" / name / "features")
    p, st = res.problem, res.state
    if not isinstance(cov, np.ndarray):
        return []
    parts, honest, kind, arr = std_parts(p, lin, lay, st, cov, meta,
                                        motion_noise(stages.get("motion"), p, meta.get("doa_time_s")))
    r0, J0, tr = truth_linearisation(work, name, p, st, lay, kinds, res, lin)
    ref, named = str(p.names[p.ref]), set((cal["report"].get("verdict") or {}).get("flagged_arrays") or [])
    bound = BD.WIDE.get(name.rsplit("_", 1)[0], BD.BOUND)
    out = []
    for i, a in enumerate(map(str, p.names)):
        ix = lay.x[i]
        if i == p.ref or np.any(ix < 0):
            continue
        H = cov[:, ix]
        var = {t: float(np.sum((g @ H) ** 2)) for t, g in parts.items()}
        total = float(np.trace(honest[np.ix_(ix, ix)]))
        assert abs(sum(var.values()) / total - 1.0) < 1e-6, "the parts do not add up to the std"
        rows = np.array([group_of(k, b, a, ref) for k, b in zip(kind, arr)])
        claim = defaultdict(float)
        for t, v in var.items():
            claim[group_of(*t.split(":"), a, ref)] += v
        moved = {g: -H.T @ (J0[rows == g].T @ r0[rows == g]) for g in set(rows)}
        error = {g: float(np.sum(v ** 2)) for g, v in moved.items() if g != "tdoa"}
        linear = float(np.linalg.norm(sum(moved.values())))
        err = st.x[i] - tr.x[i]
        turn = np.degrees(np.arccos(np.clip((np.trace(st.R[i].T @ tr.R[i]) - 1.0) / 2.0, -1.0, 1.0)))
        out.append({"session": name, "array": a, "std_cm": 100 * median_error(np.sqrt(np.diag(honest)[ix])),
                    "err_cm": 100 * float(np.linalg.norm(err)), "linear_cm": 100 * linear, "named": a in named,
                    "off": bool(np.linalg.norm(err) > bound[0] or turn > bound[1]),
                    "parts": {t: v / total for t, v in sorted(var.items(), key=lambda x: -x[1])[:3]},
                    "claim": dict(claim), "error": error})
    return out


def pooled(rows, label):
    """√(Σ error² / Σ claim) per group, and each group's share of the claimed variance."""
    e, c = defaultdict(float), defaultdict(float)
    for r in rows:
        for g, v in r["claim"].items():
            c[g] += v
            e[g] += r["error"].get(g, np.nan)
    total = sum(c.values())
    print(f"{label:26s} {len(rows):3d} arrays | " + "  ".join(
        f"{g} {np.sqrt(e[g] / c[g]) if g != 'tdoa' else np.nan:.2f} ({c[g] / total:.2f})" for g in sorted(c) if c[g] > 0))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("sessions", nargs="+")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for name in args.sessions:
        for r in session(args.work, name):
            rows.append(r)
            print(f"{name} {r['array']}: error {r['err_cm']:.1f} cm (linear {r['linear_cm']:.1f}), std {r['std_cm']:.1f}"
                  f"{' named' if r['named'] else ''}{' off' if r['off'] else ''} | "
                  + " ".join(f"{t}={v:.2f}" for t, v in r["parts"].items()) + " | error/√claim "
                  + " ".join(f"{g} {np.sqrt(r['error'][g] / v):.2f}" for g, v in r["claim"].items()
                             if g in r["error"] and v > 0), flush=True)
    print("\nper group: error / √claim pooled (share of the claimed variance); tdoa not compared")
    frame = pd.DataFrame(rows)
    for preset, d in frame.groupby(frame["session"].str.rsplit("_", n=1).str[0]):
        pooled(d.to_dict("records"), preset)
        pooled(d[d.named & ~d.off].to_dict("records"), preset + " over-named")
    pooled(rows, "all")
    pooled(frame[frame.named & ~frame.off].to_dict("records"), "all over-named")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
