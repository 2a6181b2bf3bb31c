"""Whose shared DOA rotation widens the position std, and is its width the error's (issue 27's over-naming).

    python benchmarks/diag_shared_rotation.py WORK SESSION...    # WORK/SESSION: `calib simulate`; WORK/runs/SESSION: `calib run`

A rotation common to a non-reference array's DOAs is absorbed by its orientation and moves no position
(tests/test_honest_std.py); the reference's turns the map. So the shared term's part of each array's position
std is the reference's alone. Per session: the rotation that best turns the reference's kept DOAs onto the true
directions (ω, deg per axis; "noise": its part that the rows' own scatter about it explains) beside the term's
stated std; per array: the position error split by the final linearisation into the part that ω makes
(H⁻¹ Jᵀ G ω, G the reference's whitened rows per unit turn: the rows err by −ω) and the rest, each beside its std term (the honest
covariance's with and without the reference's block of ``shared_doa_rows``), as median errors (cm). The last
line pools error / std: an honest term reads ~1 in the median. The part ω makes holds the reference rows' own
noise too (the plain covariance's, not the term's): where ω is within its "noise" the ratio overstates the term's
share (deploy 511-512: ω ≈ noise, part / term 2-5). An array without a std (dropped) prints 0.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from calib.estimator import uncertainty as U
from calib.estimator import variance as V
from calib.estimator.motion import motion_noise
from calib.estimator.problem import make_layout
from calib.estimator.solver import linearise
from calib.estimator.verdict import median_error
from calib.pipeline.run import estimate_defaults, estimate_features

CAL = importlib.import_module("calib.estimator.calibrate")


def final_solve(features_dir, findings=True):
    """(calibration, the final JointResult, kinds, stages, meta) of `calib run`'s estimate of ``features_dir``
    (``findings``: with the set-up findings the features show, as `calib run`)."""
    seen, inner = {}, CAL._full_outputs

    def grab(res, kinds, stages, *a, **k):
        seen.update(res=res, kinds=kinds, stages=stages, meta=k.get("meta") or {})
        return inner(res, kinds, stages, *a, **k)
    CAL._full_outputs = grab
    try:
        cal, _ = estimate_features(features_dir, estimate_defaults(), findings=findings)
    finally:
        CAL._full_outputs = inner
    return cal, seen["res"], seen["kinds"], seen["stages"], seen["meta"]


def final_linearisation(features_dir, findings=True):
    """:func:`final_solve` (``findings`` as there) and its linearisation at the final state: (cal, res, kinds,
    stages, meta, lay, lin, cov), ``cov`` the estimator's covariance of the kept rows (not an ndarray when it
    failed)."""
    cal, res, kinds, stages, meta = final_solve(features_dir, findings)
    lay = make_layout(res.problem)
    lin = linearise(res.problem, res.state, lay, kinds, mask=res.mask)
    return cal, res, kinds, stages, meta, lay, lin, U.covariance(lin.J[lin.w > 0], lay.n, lay)


def cross(u):
    ux = np.zeros((len(u), 3, 3))
    ux[:, 0, 1], ux[:, 0, 2], ux[:, 1, 2] = -u[:, 2], u[:, 1], -u[:, 0]
    return ux - np.transpose(ux, (0, 2, 1))


def reference_rows(p, lin):
    """(kept reference DOA rows k, their whitened rows per unit ω (M, 3), the doa factor's first row)."""
    kinds = [f.kind for f in lin.factors]
    start = sum(len(f.r) for f in lin.factors[:kinds.index("doa")])
    n = 3 * len(p.doa.u)
    k = np.flatnonzero((lin.w[start:start + n] > 0).reshape(-1, 3).all(axis=1) & (p.doa.arr == p.ref))
    sig = np.broadcast_to(lin.factors[kinds.index("doa")].row_sigma, (n,))
    G = np.zeros((len(lin.r), 3))
    rows = start + 3 * k[:, None] + np.arange(3)
    G[rows] = np.einsum("kab,kbc->kac", p.doa.axes[k], cross(p.doa.u[k])) / sig[rows - start][:, :, None]
    return k, G


def session(work, name):
    """Print the session's lines; return [(error part / its std term) for the reference's part, the rest]."""
    cal, res, kinds, stages, meta, lay, lin, cov = final_linearisation(work / "runs" / name / "features")
    p, st = res.problem, res.state
    keep = lin.w > 0
    if not isinstance(cov, np.ndarray) or not len(p.doa.u):
        return []
    vel = U.velocity_rows(lin, lay, motion_noise(stages.get("motion"), p, meta.get("doa_time_s")))
    fac = V.covariance_factors(p, lin, cov, lower=V.LOWERED_KINDS + (U.ARRIVAL_KINDS if vel is not None else ()))
    shared = U._sum_shared(U.shared_doa_rows(p, lin, V.covariance_factors(p, lin, cov)),
                           U.shared_cone_rows(p, lin, st, V.covariance_factors(p, lin, cov)))
    without_ref = shared.copy()
    without_ref[:, 3 * p.ref:3 * p.ref + 3] = 0.0
    args = (p, lin, cov, fac, bool(meta.get("tdoa_shared_arrivals")), U.plane_normals(meta, p.names), vel)
    honest, rest_cov = U.sandwich_covariance(*args, shared), U.sandwich_covariance(*args, without_ref)
    k, G = reference_rows(p, lin)
    truth = pd.read_csv(work / name / "truth" / "sources.csv").set_index("event")
    s = truth.loc[np.asarray(p.events)[p.doa.ev[k]], ["x", "y", "z"]].to_numpy(float)
    A = -cross(p.doa.u[k]).reshape(-1, 3)
    e = (s / np.linalg.norm(s, axis=1, keepdims=True) - p.doa.u[k]).ravel()
    omega = np.linalg.lstsq(A, e, rcond=None)[0]
    noise = np.sqrt(np.sum((e - A @ omega) ** 2) / max(2 * len(k) - 3, 1) * np.diag(np.linalg.pinv(A.T @ A)))
    print(f"== {name}: reference {p.names[p.ref]} ω {np.round(np.degrees(omega), 2)}° (noise "
          f"{np.round(np.degrees(noise), 2)}°)")
    return _arrays(work, name, cal, p, lay, cov, np.asarray(lin.J), keep, G @ omega, honest, rest_cov)


def _arrays(work, name, cal, p, lay, cov, J, keep, dr, honest, rest_cov):
    part = cov @ (J[keep].T @ dr[keep])   # the rows err by the turn −ω (ω turns them onto the truth)
    tru = pd.read_csv(work / name / "truth" / "arrays.csv").astype({"array": str}).set_index("array")
    est = cal["arrays"].astype({"array": str}).set_index("array")
    out = []
    for i, a in enumerate(map(str, p.names)):
        ix = lay.x[i]
        if i == p.ref or np.any(ix < 0) or a not in est.index:
            continue
        err = est.loc[a, ["x", "y", "z"]].to_numpy(float) - tru.loc[a, ["x", "y", "z"]].to_numpy(float)
        sd_ref = median_error(np.sqrt(np.maximum(np.diag(honest)[ix] - np.diag(rest_cov)[ix], 0.0)))
        sd_rest = median_error(np.sqrt(np.diag(rest_cov)[ix]))
        ref_part, rest = np.linalg.norm(part[ix]), np.linalg.norm(err - part[ix])
        print(f"   {a}: error {100 * np.linalg.norm(err):.1f} cm, std {100 * median_error(np.sqrt(np.diag(honest)[ix])):.1f}"
              f" | reference's rotation {100 * ref_part:.1f} (its term {100 * sd_ref:.1f}) | rest {100 * rest:.1f} "
              f"(std without it {100 * sd_rest:.1f})")
        out.append((ref_part / max(sd_ref, 1e-9), rest / sd_rest))
    return out


def main():
    work = Path(sys.argv[1])
    z = np.array([r for name in sys.argv[2:] for r in session(work, name)])
    if len(z):
        print(f"pooled over {len(z)} arrays, median (share > 1): reference's part / its term {np.median(z[:, 0]):.2f} "
              f"({np.mean(z[:, 0] > 1):.0%}); rest / its std {np.median(z[:, 1]):.2f} ({np.mean(z[:, 1] > 1):.0%})")


if __name__ == "__main__":
    main()
