"""What makes each array's orientation std, and do those sources err that much (issue 27's orientation over-naming)?

    python benchmarks/diag_rot_sources.py WORK SESSION...   # WORK/SESSION: `calib simulate`; WORK/runs/SESSION: `calib run`

The orientation counterpart of diag_std_sources (same terms, ``std_parts``): per non-reference array with a free
rotation, its rotation std per axis (array frame, right perturbation R Exp(φ)) against its true error φ =
Log(R_trueᵀ R_est) per axis, the three largest terms' shares of its rotation variance, the part of the planar DOA
term that the near-plane fold adds (the same term with FOLD_SIGMAS = 0, subtracted), and per group the linearised
error its rows make at the truth against the group's claim. Pooled: RMS of error / std per axis over all arrays,
per class (planar, 3-D, linear), and √(Σ error² / Σ claim) per group. What-ifs (the covariance only, same solve):
``excess`` the own shared rotation keyed on the scatter less the rows' own sigma in quadrature, ``floor_only``
(SHARED_DOA_SCATTER = 0), ``no_shared`` (no own shared rotation); "named>1.5" counts arrays whose rotation std's
median_error would exceed 1.5° (position naming not counted). Results: docs/results.md (h52o).
"""
from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import diag_std_sources as DS   # noqa: E402

from calib.estimator import uncertainty as U
from calib.estimator.motion import motion_noise
from calib.estimator.verdict import median_error


def session(work, name):
    cal, res, kinds, stages, meta, lay, lin, cov = DS.final_linearisation(work / "runs" / name / "features")
    p, st = res.problem, res.state
    motion = motion_noise(stages.get("motion"), p, meta.get("doa_time_s"))
    parts, honest, kind, arr = DS.std_parts(p, lin, lay, st, cov, meta, motion)
    keep_fold, keep_scatter = U.FOLD_SIGMAS, U.SHARED_DOA_SCATTER
    U.FOLD_SIGMAS = 0.0
    try:
        nofold, _, _, _ = DS.std_parts(p, lin, lay, st, cov, meta, motion)
    finally:
        U.FOLD_SIGMAS = keep_fold
    alt = {}
    plain_scatter = U._row_scatter

    def excess_scatter(e, ux, sig):   # the scatter beyond the rows' own sigma (a candidate: noise is not shared)
        return float(np.sqrt(max(plain_scatter(e, ux, sig) ** 2 - float(np.median(sig)) ** 2, 0.0)))
    U._row_scatter = excess_scatter
    try:
        alt["excess"] = DS.std_parts(p, lin, lay, st, cov, meta, motion)[1]
    finally:
        U._row_scatter = plain_scatter
    for label, key, value in (("floor_only", "SHARED_DOA_SCATTER", 0.0), ("no_shared", "SHARED_DOA_FRACTION", 0.0)):
        keep_value = getattr(U, key)
        setattr(U, key, value)
        if label == "no_shared":
            U.SHARED_DOA_SCATTER = 0.0
        try:
            alt[label] = DS.std_parts(p, lin, lay, st, cov, meta, motion)[1]
        finally:
            setattr(U, key, keep_value)
            U.SHARED_DOA_SCATTER = keep_scatter
    r0, J0, tr = DS.truth_linearisation(work, name, p, st, lay, kinds, res, lin)
    ref, named = str(p.names[p.ref]), set((cal["report"].get("verdict") or {}).get("flagged_arrays") or [])
    normals = U.plane_normals(meta, p.names)
    out = []
    for i, a in enumerate(map(str, p.names)):
        ix = lay.rot[i]
        if i == p.ref or np.any(ix < 0):
            continue
        H = cov[:, ix]
        var = {t: np.sum((g @ H) ** 2, axis=0) for t, g in parts.items()}
        var0 = {t: np.sum((g @ H) ** 2, axis=0) for t, g in nofold.items()}
        std = np.sqrt(np.diag(honest)[ix])
        if not np.all(np.isfinite(std) & (std > 0)):
            continue   # (no std: the array was dropped from the covariance)
        total = float(np.sum(std ** 2))
        assert abs(sum(float(v.sum()) for v in var.values()) / total - 1.0) < 1e-6, "the parts do not add up to the std"
        rows = np.array([DS.group_of(k, b, a, ref) for k, b in zip(kind, arr)])
        claim = defaultdict(float)
        for t, v in var.items():
            claim[DS.group_of(*t.split(":"), a, ref)] += float(v.sum())
        moved = {g: -H.T @ (J0[rows == g].T @ r0[rows == g]) for g in set(rows)}
        error = {g: float(np.sum(v ** 2)) for g, v in moved.items() if g != "tdoa"}
        phi = Rotation.from_matrix(tr.R[i].T @ st.R[i]).as_rotvec()
        fold = sum(float(var[t].sum() - var0.get(t, 0).sum()) for t in var if t.startswith("doa_planar"))
        cls = "linear" if p.rot_fixed_axis[i] >= 0 else ("planar" if np.any(normals[i] != 0) else "3d")
        z = phi @ np.linalg.solve(honest[np.ix_(ix, ix)], phi)
        z_alt = {k: float(np.sqrt(phi @ np.linalg.solve(c[np.ix_(ix, ix)], phi) / 3)) for k, c in alt.items()}
        med_alt = {k: float(np.degrees(median_error(np.sqrt(np.diag(c)[ix])))) for k, c in alt.items()}
        out.append({"session": name, "array": a, "class": cls, "named": a in named,
                    "std_deg": np.degrees(std), "err_deg": np.degrees(phi), "linear_deg": np.degrees(sum(moved.values())),
                    "med_std": np.degrees(median_error(std)), "err_norm": float(np.degrees(np.linalg.norm(phi))),
                    "z3": float(np.sqrt(z / 3)), "z_alt": z_alt, "med_alt": med_alt, "fold_share": fold / total,
                    "parts": {t: float(v.sum()) / total for t, v in sorted(var.items(), key=lambda x: -x[1].sum())[:4]},
                    "claim": dict(claim), "error": error})
    return out


def main(argv=None):
    work, names = Path(sys.argv[1]), sys.argv[2:]
    rows = []
    for name in names:
        for r in session(work, name):
            rows.append(r)
            print(f"{name} {r['array']} {r['class']}{' NAMED' if r['named'] else ''}: err {r['err_norm']:.2f}° "
                  f"per axis {np.round(r['err_deg'], 2)} (lin {np.round(r['linear_deg'], 2)}) std {np.round(r['std_deg'], 2)} "
                  f"median_err {r['med_std']:.2f}° z {r['z3']:.2f} alt " + " ".join(f"{k} z {r['z_alt'][k]:.2f} med {r['med_alt'][k]:.2f}" for k in r['z_alt']) + f" fold {r['fold_share']:.2f} | "
                  + " ".join(f"{t}={v:.2f}" for t, v in r["parts"].items()) + " | err/√claim "
                  + " ".join(f"{g} {np.sqrt(r['error'][g] / v):.2f}" for g, v in r["claim"].items()
                             if g in r["error"] and v > 0), flush=True)
    f = pd.DataFrame(rows)
    for cls, d in list(f.groupby("class")) + [("all", f), ("named", f[f.named])]:
        if d.empty:
            continue
        e, s = np.concatenate(d.err_deg.values), np.concatenate(d.std_deg.values)
        c, g = defaultdict(float), defaultdict(float)
        for r in d.to_dict("records"):
            for k, v in r["claim"].items():
                c[k] += v
                g[k] += r["error"].get(k, np.nan)
        print(f"{cls:7s} {len(d):3d} arrays: err/std RMS per axis {np.sqrt(np.mean((e / s) ** 2)):.2f} "
              f"z3 RMS {np.sqrt(np.mean(d.z3 ** 2)):.2f} max {d.z3.max():.2f} "
              + " ".join(f"[{k}: z RMS {np.sqrt(np.mean([z[k] ** 2 for z in d.z_alt])):.2f} max {max(z[k] for z in d.z_alt):.2f} named>1.5 {sum(m[k] > 1.5 for m in d.med_alt)}]" for k in ("excess", "floor_only", "no_shared")) + f" named now {(d.med_std > 1.5).sum()}"
              + f" fold share {d.fold_share.mean():.2f} | "
              + "  ".join(f"{k} {np.sqrt(g[k] / c[k]):.2f} ({c[k] / sum(c.values()):.2f})" for k in sorted(c)
                          if c[k] > 0 and k != "tdoa"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
