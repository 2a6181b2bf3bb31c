"""Does anything an array's own DOA rows show predict the rotation they truly share (issue 27's over-naming)?

    python benchmarks/diag_shared_predictors.py OUT.pkl WORK:SESSION...   # WORK/SESSION: `calib simulate`; WORK/runs/SESSION: `calib run`
    python benchmarks/diag_shared_predictors.py OUT.pkl                    # the fits again, from OUT.pkl

Per array with ≥ 3 kept DOA rows of `calib run`'s final solve: the rotation ω that best turns its kept DOAs onto the
simulator's true directions (array frame; :func:`true_shared_rotation`, a planar board's true direction mirrored to
its measured side of the mic plane; a moving source at its emission, where the solve's turned DOAs look) with the
part its rows' own rotation-removed errors explain (``noise``, taken as independent rows), beside the predictors the
data hold: the scatter about the fit (``uncertainty._row_scatter``) over the rows' stated sigma (``chi``), the share
of rows flagged ``doa_reflection``, of rows the frontend flagged ``nlos`` / ``occluded`` (``blocked``, doa.csv, kept
or not), the directions' spread (2 (1 − |mean u|), rad²: a narrow cone vs sources all around), their number. Then
for each candidate std of the shared term (``MODELS``), ω per axis over √(std² + noise²) (planar boards: the axis
along their normal alone; their tilt is the planar rows' elevation, modelled elsewhere): RMS, |z| > 3, and the one
free constant's maximum-likelihood value on even seeds, read on odd seeds; and each predictor's rank correlation
with the shared part.
Results: docs/results.md (h53s).
"""
from __future__ import annotations

import pickle
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_shared_rotation import cross, final_linearisation   # noqa: E402

from calib.estimator import uncertainty as U
from calib.estimator import variance as V
from calib.pipeline.formats.io import read_truth

BLOCKED = 0.1   # an array with more than this share of its DOA rows flagged nlos / occluded sees the source around things


def true_shared_rotation(u, u_true):
    """(ω (3,), noise (3,)): the rotation (rad, small) that best turns the measured directions ``u`` (n, 3) onto
    ``u_true`` (u_true ≈ u + ω × u, least squares), and the std per axis that its rows' rotation-removed errors,
    taken as independent (each row's own size, both tangential axes alike), give ω."""
    A = cross(u).reshape(-1, 3)
    e = (u - u_true).ravel()
    w = np.linalg.lstsq(A, e, rcond=None)[0]
    q = np.sum((e - A @ w).reshape(-1, 3) ** 2, axis=1)
    dof = len(u) / max(len(u) - 1.5, 1.0)   # the rotation absorbs 3 of the 2n tangential residuals
    P = np.linalg.pinv(A)
    return w, np.sqrt(np.sum((P * np.repeat(np.sqrt(q / 2 * dof), 3)[None]) ** 2, axis=1))


def blocked_share(work, name):
    """{array: share of its doa.csv rows flagged nlos or occluded}."""
    d = pd.read_csv(work / "runs" / name / "features" / "doa.csv", dtype={"array": str})
    bad = d["flag"].fillna("").str.contains("nlos|occluded")
    return bad.groupby(d["array"]).mean().to_dict()


def session(work, name):
    """One record per array with ≥ 3 kept DOA rows."""
    cal, res, kinds, stages, meta, lay, lin, cov = final_linearisation(work / "runs" / name / "features")
    p, st = res.problem, res.state
    fac = V.covariance_factors(p, lin, cov) if isinstance(cov, np.ndarray) else {}
    truth = read_truth(work / name / "truth")
    tr = U.state_from_frames(p, truth["arrays"], truth["sources"])
    normals, blocked = U.plane_normals(meta, p.names), blocked_share(work, name)
    out = []
    for f, start, n in U._kind_blocks(lin, "doa"):
        keep = (lin.w[start:start + n] > 0).reshape(-1, 3).all(axis=1)
        arr, u, m = p.doa.arr, p.doa.u, n // 3
        d = tr.s[p.doa.ev] - tr.x[arr]
        ut = np.einsum("kba,kb->ka", tr.R[arr], d / np.linalg.norm(d, axis=1, keepdims=True))
        nv = normals[arr]
        side = np.einsum("ka,ka->k", nv, ut) * np.einsum("ka,ka->k", nv, u) < 0   # a planar board's mirror side
        ut = np.where(side[:, None], ut - 2 * np.einsum("ka,ka->k", nv, ut)[:, None] * nv, ut)
        e = np.einsum("kba,kb->ka", p.doa.axes, (f.r * f.row_sigma).reshape(m, 3))
        sig0 = p.sigma["doa"] * p.doa.scale
        iso = fac.get("doa", np.ones(p.N))
        refl = np.zeros(m, bool) if p.doa.reflection is None else np.asarray(p.doa.reflection, bool)
        for i in np.unique(arr[keep]):
            k = np.flatnonzero(keep & (arr == i))
            if len(k) < 3:
                continue
            w, noise = true_shared_rotation(u[k], ut[k])
            scatter = U._row_scatter(e[k], cross(u[k]), sig0[k])
            out.append({"session": name, "preset": name.rsplit("_", 1)[0], "seed": int(name.rsplit("_", 1)[1]),
                        "array": str(p.names[i]), "ref": bool(i == p.ref), "planar": bool(np.any(normals[i] != 0)),
                        "n": len(k), "refl": float(refl[k].mean()), "blocked": float(blocked.get(str(p.names[i]), 0.0)),
                        "sig0": float(np.median(sig0[k])), "sd": float(np.median(sig0[k] * np.sqrt(iso[i]))),
                        "scatter": scatter, "chi": scatter / float(np.median(sig0[k])), "w": w, "noise": noise,
                        "spread": float(2 * (1 - np.linalg.norm(u[k].mean(axis=0))))})
    return out


def _excess(r, k):
    return k * r.sig0 * np.sqrt(np.maximum(r.chi ** 2 - 1.0, 0.0))


MODELS = {   # (std of the shared term (rad) per array, free constant's start or None)
    "current": (lambda r, k: np.maximum(U.SHARED_DOA_FRACTION * r.sd, U.SHARED_DOA_SCATTER * r.scatter), None),
    "floor": (lambda r, k: U.SHARED_DOA_FRACTION * r.sd, None),
    "scatter_k": (lambda r, k: np.maximum(U.SHARED_DOA_FRACTION * r.sd, k * r.scatter), 0.89),
    "excess_k": (lambda r, k: np.maximum(U.SHARED_DOA_FRACTION * r.sd, _excess(r, k)), 0.89),
    "flag": (lambda r, k: r.sd * np.where(r.refl > U.REFLECTION_MAJORITY, U.SHARED_CONE_FRACTION_REFLECTION,
                                          U.SHARED_DOA_FRACTION), None),
}


def zscores(f, std):
    """ω per axis over √(std² + noise²) (planar boards: the normal axis alone), flattened."""
    w, noise = np.stack(f.w.values), np.stack(f.noise.values)
    z = w / np.sqrt(np.asarray(std)[:, None] ** 2 + noise ** 2)
    axis = np.ones_like(z, bool)
    axis[f.planar.values, :2] = False   # (the boards' mic planes are their frames' xy planes)
    return z[axis]


def report(f, label):
    """Per model: the constant fitted on even seeds (Gaussian likelihood), z RMS / |z| > 3 / max on each half."""
    fit, check = f[f.seed % 2 == 0], f[f.seed % 2 == 1]
    print(f"== {label}: {len(fit)} arrays (even seeds) / {len(check)} (odd)")
    for name, (std, k0) in MODELS.items():
        k = k0
        if k0 is not None:
            k = minimize_scalar(lambda c: _nll(fit, std(fit, c)), bounds=(0, 5), method="bounded").x
        cells = []
        for half, g in (("even", fit), ("odd", check)):
            z = zscores(g, std(g, k))
            cells.append(f"{half} RMS {np.sqrt(np.mean(z ** 2)):.2f} >3 {int(np.sum(np.abs(z) > 3))} max {np.abs(z).max():.1f}")
        presets = "  ".join(f"{p} {np.sqrt(np.mean(zscores(g, std(g, k)) ** 2)):.2f}" for p, g in check.groupby("preset"))
        print(f"  {name:9s} {'' if k is None else f'k {k:.2f}':7s} " + " | ".join(cells) + f" || odd per preset: {presets}")


def _nll(f, std):
    w, noise = np.stack(f.w.values), np.stack(f.noise.values)
    v = np.asarray(std)[:, None] ** 2 + noise ** 2
    axis = np.ones_like(v, bool)
    axis[f.planar.values, :2] = False
    return np.sum((np.log(v) + w ** 2 / v)[axis])


def predictor_ranks(f):
    """Spearman rank correlation of each predictor with the array's shared part beyond its noise (mean over the
    axes read of ω² − noise²) over its scatter² and over its rows' sigma²."""
    w, noise = np.stack(f.w.values), np.stack(f.noise.values)
    axis = np.ones_like(w, bool)
    axis[f.planar.values, :2] = False
    shared2 = np.nanmean(np.where(axis, w ** 2 - noise ** 2, np.nan), axis=1)
    for key in ("chi", "refl", "blocked", "spread", "n", "sig0"):
        print(f"  {key:8s} rank correlation with shared² / scatter² {spearmanr(f[key], shared2 / f.scatter ** 2)[0]:+.2f}, "
              f"/ σ² {spearmanr(f[key], shared2 / f.sig0 ** 2)[0]:+.2f}")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    out, pairs = Path(argv[0]), [a.rsplit(":", 1) for a in argv[1:]]
    if pairs:
        rows = [r for work, name in pairs for r in session(Path(work), name)]
        pickle.dump(rows, open(out, "wb"))
    f = pd.DataFrame(pickle.load(open(out, "rb")))
    others = f[~f.ref]
    report(others, "non-reference arrays")
    report(others[others.blocked > BLOCKED], f"non-reference, > {BLOCKED:.0%} of rows nlos / occluded")
    report(others[others.blocked <= BLOCKED], f"non-reference, clear (≤ {BLOCKED:.0%})")
    report(f[f.ref], "references (their term today: flag)")
    print("== non-reference arrays' predictors")
    predictor_ranks(others)
    return 0


if __name__ == "__main__":
    sys.exit(main())
