"""Do an array's OWN DOA rows move its position by more than the model's own-DOA share of its std (issue 27)?

    python benchmarks/diag_own_doa.py WORK SESSION...    # WORK/SESSION: `calib simulate`; WORK/runs/SESSION: `calib run`

Per non-reference array with kept DOA rows: the position error its own rows make, −H⁻¹ Jᵀ r (r: those rows'
whitened residuals at the TRUE geometry, H⁻¹ the plain covariance of the final linearisation), beside their share
of the honest position std (the honest covariance less the same with those rows' Jacobian zeroed), as median
errors (cm); its class (planar or not, the median true elevation above the mic plane, the share of rows flagged
``doa_reflection``). The last lines pool |error| / |share| (per-axis stds in quadrature; an honest share reads
RMS ~1) per class. Issue 27 asked whether the reference's over-wide shared term was covering own-DOA errors the
model holds nowhere else: the class of mostly flagged planar arrays seeing sources well above their plane (the
ceiling arrays that went off-and-unnamed when that term shrank) reads RMS 0.87 on lshape/moving/office/robot
500-504 (docs/results.md).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.estimator import uncertainty as U
from calib.estimator import variance as V
from calib.estimator.motion import motion_noise
from calib.estimator.verdict import median_error

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_shared_rotation import final_linearisation  # noqa: E402

HIGH_ELEVATION_DEG = 30.0   # a planar array whose sources sit mostly above this (a ceiling array) vs near its plane
MOSTLY_FLAGGED = 0.5        # as uncertainty.REFLECTION_MAJORITY


def session(work, name):
    """Print the session's arrays; return [(class, |own error| / |own share|)]."""
    cal, res, kinds, stages, meta, lay, lin, cov = final_linearisation(work / "runs" / name / "features")
    p, st = res.problem, res.state
    if not isinstance(cov, np.ndarray) or not len(p.doa.u):
        return []
    vel = U.velocity_rows(lin, lay, motion_noise(stages.get("motion"), p, meta.get("doa_time_s")))
    fac = V.covariance_factors(p, lin, cov, lower=V.LOWERED_KINDS + (U.ARRIVAL_KINDS if vel is not None else ()))
    stated = V.covariance_factors(p, lin, cov)
    shared = U._sum_shared(U.shared_doa_rows(p, lin, stated), U.shared_cone_rows(p, lin, st, stated))
    normals = U.plane_normals(meta, p.names)
    args = (p, lin, cov, fac, bool(meta.get("tdoa_shared_arrivals")), normals, vel)
    honest = np.diag(U.sandwich_covariance(*args, shared))
    J = lin.J.toarray() if hasattr(lin.J, "toarray") else np.array(lin.J)
    f, start = next((g, s) for g, s, _ in U._kind_blocks(lin, "doa"))
    m = len(p.doa.u)
    keep = (lin.w[start:start + 3 * m] > 0).reshape(-1, 3).all(axis=1)
    sig = np.broadcast_to(f.row_sigma, 3 * m).reshape(m, 3)
    flagged = np.zeros(m, bool) if p.doa.reflection is None else np.asarray(p.doa.reflection, bool)
    tru = pd.read_csv(work / name / "truth" / "arrays.csv").astype({"array": str}).set_index("array")
    src = pd.read_csv(work / name / "truth" / "sources.csv").set_index("event")
    out = []
    for i, a in enumerate(map(str, p.names)):
        k = np.flatnonzero(keep & (p.doa.arr == i))
        ix = lay.x[i]
        if i == p.ref or len(k) < 3 or np.any(ix < 0):
            continue
        rot = Rotation.from_quat(tru.loc[a, ["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True).as_matrix()
        d = (src.loc[np.asarray(p.events)[p.doa.ev[k]], ["x", "y", "z"]].to_numpy(float)
             - tru.loc[a, ["x", "y", "z"]].to_numpy(float)) @ rot
        u_true = d / np.linalg.norm(d, axis=1, keepdims=True)
        r_true = (np.einsum("kab,kb->ka", p.doa.axes[k], u_true - p.doa.u[k]) / sig[k]).ravel()
        rows = (start + 3 * k[:, None] + np.arange(3)).ravel()
        error = -(cov @ (J[rows].T @ r_true))[ix]
        J_without = J.copy()
        J_without[start + np.flatnonzero(np.repeat(p.doa.arr == i, 3))] = 0.0
        without = np.diag(U.sandwich_covariance(p, lin._replace(J=J_without), *args[2:], shared))
        share = np.sqrt(np.maximum(honest[ix] - without[ix], 0.0))
        planar = bool(np.any(normals[i]))
        el = np.degrees(np.median(np.abs(np.arcsin(np.clip(u_true @ normals[i], -1, 1))))) if planar else np.nan
        cls = ("planar " + ("high" if el > HIGH_ELEVATION_DEG else "low") if planar else "3-D") + \
              (", mostly flagged" if flagged[k].mean() > MOSTLY_FLAGGED else ", few flagged")
        print(f"   {name} {a}: {cls:26s} elevation {el:5.1f}°  own rows' error {100 * np.linalg.norm(error):.2f} cm, "
              f"their share {100 * median_error(share):.2f} (std {100 * median_error(np.sqrt(honest[ix])):.2f})")
        out.append((cls, np.linalg.norm(error) / max(np.linalg.norm(share), 1e-9)))
    return out


def main():
    work = Path(sys.argv[1])
    rows = [r for name in sys.argv[2:] for r in session(work, name)]
    for cls in sorted({c for c, _ in rows}):
        q = np.array([x for c, x in rows if c == cls])
        print(f"{cls:26s} {len(q):3d} arrays: |own error| / |own share| RMS {np.sqrt(np.mean(q ** 2)):.2f} "
              f"median {np.median(q):.2f} (> 2: {np.sum(q > 2)})")


if __name__ == "__main__":
    main()
