"""Are a planar array's DOA errors at the truth a smooth field of direction (issue 27's ceiling-array misses)?

    python benchmarks/diag_doa_field.py WORK SESSION...   # WORK/SESSION: `calib simulate`; WORK/runs/SESSION features
    python benchmarks/diag_doa_field.py WORK SESSION... --json OUT.json

Per planar board (mics in its z = 0 plane) whose true source directions are mostly > 30° off that plane: each DOA
row's error at the simulator's truth (true pose, true source; a moving source at t_emit + meta ``doa_time_s`` on
truth/trajectory.csv), in the array frame as (azimuth, elevation) arc components, the truth folded into the board's
hemisphere. Fitted by weighted least squares (rows by their stated sigma_deg, as the solve; --whiten: each
component by its scatter after the richest model) with
nested low-order fields: a rigid rotation (3); + an in-plane scale k of |u_xy| (1: a wrong aperture, elevation
error toward the normal); + an elevation offset (1); + a general linear field P(u) M u (8); the array's pose
(rotation + displacement δx with the sources held at the truth, δu = −P(u) Rᵀδx / d: what the joint solve's
position absorbs); + a DOA look-time offset δt along the source's velocity (δu = P(u) Rᵀv δt / d, moving sources).
Printed: each model's fraction of the error explained and its F statistic against the model it extends (pure
independent noise: F ~ 1, explained ~ p / 2n), the fitted δx (cm), k and δt.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats
from scipy.spatial.transform import Rotation

OFF_PLANE = 0.5          # median |u_z| above sin 30°: sources mostly well off the board's plane
MIN_ROWS = 8             # fewer rows cannot hold the richest model (14 parameters on 2 n numbers)
NESTED = {"rot": (None, ("rot",)), "rot+k": ("rot", ("rot", "scale")), "rot+el": ("rot", ("rot", "elev")),
          "rot+lin": ("rot", ("rot", "lin")), "pose": ("rot", ("rot", "pos")),
          "pose+k": ("pose", ("rot", "pos", "scale")), "pose+lin": ("pose", ("rot", "pos", "lin")),
          "rot+dt": ("rot", ("rot", "vel")), "pose+dt": ("pose", ("rot", "pos", "vel"))}


def tangent(u):
    """(n, 2, 3) azimuth and elevation unit vectors at directions u (board normal z, elevation toward +z·sign u_z)."""
    phi = np.arctan2(u[:, 1], u[:, 0])
    az = np.stack([-np.sin(phi), np.cos(phi), 0 * phi], 1)
    el = np.cross(u, az)
    el *= np.where(el[:, 2] * np.sign(u[:, 2]) >= 0, 1.0, -1.0)[:, None]
    return np.stack([az, el], 1)


def fields(u, d, v=None):
    """{name: (n, 3, p) δu per unit parameter} at true directions u (array frame), distances d, velocities v."""
    P = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
    uz = np.where(np.abs(u[:, 2]) < 1e-3, 1e-3, u[:, 2])
    out = {"rot": np.stack([np.cross(np.eye(3)[k][None], u) for k in range(3)], 2),
           "pos": -P / d[:, None, None],
           "scale": np.stack([u[:, 0], u[:, 1], -(u[:, 0] ** 2 + u[:, 1] ** 2) / uz], 1)[:, :, None],
           "elev": tangent(u)[:, 1, :, None],
           "lin": np.stack([np.einsum("nij,nj->ni", P, np.eye(3)[a][None] * u[:, b:b + 1])
                            for a in range(3) for b in range(3)], 2)}
    if v is not None:
        out["vel"] = (np.einsum("nij,nj->ni", P, v) / d[:, None])[:, :, None]
    return out


def _lstsq(E, X, w):
    A = (X * w[None, :, None]).reshape(-1, X.shape[2])
    b = (E * w[None, :]).reshape(-1)
    c, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ c
    return float(r @ r), c, int(np.linalg.matrix_rank(A, tol=1e-8 * np.abs(A).max()))


def fit_fields(u0, um, d, v=None, sigma=None):
    """Per model {explained, p, F, p_value, c}: u0 true, um measured unit directions (n, 3), array frame; sigma
    (n,) the rows' stated sd (rad; the solve's weights), None: each component whitened by its own scatter."""
    T = tangent(u0)
    E = np.einsum("nij,nj->ni", T, um - u0)
    if sigma is not None:
        E, T = E / sigma[:, None], T / sigma[:, None, None]
    X = {k: np.einsum("nij,njp->nip", T, f) for k, f in fields(u0, d, v).items()}
    richest = np.concatenate([X["rot"], X["pos"], X["lin"]], 2)
    A = richest.reshape(-1, richest.shape[2])
    c, *_ = np.linalg.lstsq(A, E.reshape(-1), rcond=None)
    r = (E.reshape(-1) - A @ c).reshape(-1, 2)
    w = (np.ones(2) if sigma is not None else
         1.0 / np.maximum(np.sqrt(np.mean(r ** 2, 0) * len(r) / max(len(r) - richest.shape[2] / 2, 1)), 1e-9))
    total = float(np.sum((E * w) ** 2))
    fits, n2 = {}, E.size
    for m, (base, keys) in NESTED.items():
        if not all(k in X for k in keys):
            continue
        rss, c, p = _lstsq(E, np.concatenate([X[k] for k in keys], 2), w)
        b_rss, b_p = (total, 0) if base is None else (fits[base]["rss"], fits[base]["p"])
        F = ((b_rss - rss) / max(p - b_p, 1)) / (rss / max(n2 - p, 1))
        fits[m] = {"rss": rss, "p": p, "explained": 1 - rss / total, "F": F, "c": c.tolist(),
                   "p_value": float(stats.f.sf(F, max(p - b_p, 1), max(n2 - p, 1)))}
    scale = 1.0 if sigma is None else sigma[:, None]
    return fits, np.rad2deg(np.sqrt(np.mean((E * scale) ** 2, 0)))


def sources_at_doa(truth, meta, src):
    """True source positions (and velocities, None for still sources) when the DOA looks at them."""
    t_doa, tr = float(meta.get("doa_time_s") or 0.0), truth / "trajectory.csv"
    if not t_doa or not tr.exists():
        return src, None
    traj = pd.read_csv(tr)
    te = np.asarray(json.load(open(truth / "manifest.json"))["scenario"]["t_emit"])[src.index.to_numpy()] + t_doa
    at = lambda t: np.stack([np.interp(t, traj.t, traj[c]) for c in "xyz"], 1)   # noqa: E731
    step = 1e-3
    return (pd.DataFrame(at(te), index=src.index, columns=list("xyz")),
            pd.DataFrame((at(te + step) - at(te - step)) / (2 * step), index=src.index, columns=list("xyz")))


def session(work, name, weighted=True):
    """One row per off-plane planar array of session ``name`` (weighted: rows by their stated sigma_deg)."""
    feats, truth = work / "runs" / name / "features", work / name / "truth"
    meta = json.load(open(feats / "meta.json"))
    doa = pd.read_csv(feats / "doa.csv", dtype={"array": str})
    arr = pd.read_csv(truth / "arrays.csv", dtype={"array": str}).set_index("array")
    src, vel = sources_at_doa(truth, meta, pd.read_csv(truth / "sources.csv").set_index("event"))
    out = []
    for a, g in doa.groupby("array"):
        mics = np.asarray(meta["mics"][a], float)
        if len(mics) < 3 or np.ptp(mics[:, 2]) > 1e-9 or np.linalg.matrix_rank(mics - mics.mean(0)) < 2:
            continue
        R = Rotation.from_quat(arr.loc[a, ["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True).as_matrix()
        x = arr.loc[a, ["x", "y", "z"]].to_numpy(float)
        rel = (src.loc[g.event, list("xyz")].to_numpy(float) - x) @ R
        d = np.linalg.norm(rel, axis=1)
        um = g[["ux", "uy", "uz"]].to_numpy(float)
        hemi = np.sign(np.nanmedian(um[:, 2])) or 1.0
        fold = np.sign(rel[:, 2]) * hemi                        # a planar board sees ±u_z alike
        u0 = rel / d[:, None] * np.stack([np.ones_like(fold)] * 2 + [fold], 1)
        v = None if vel is None else vel.loc[g.event, list("xyz")].to_numpy(float) @ R * np.stack(
            [np.ones_like(fold)] * 2 + [fold], 1)
        sig = np.deg2rad(g["sigma_deg"].to_numpy(float)) if weighted else None
        ok = np.isfinite(um).all(1) & (np.isfinite(sig) if weighted else True)
        if ok.sum() < MIN_ROWS or np.median(np.abs(u0[ok, 2])) <= OFF_PLANE:
            continue
        fits, rms = fit_fields(u0[ok], um[ok], d[ok], None if v is None else v[ok], sig[ok] if weighted else None)
        out.append({"session": name, "array": a, "ref": bool(np.all(x == 0)), "n": int(ok.sum()),
                    "uz_med": float(np.median(np.abs(u0[ok, 2]))), "rms_az_deg": float(rms[0]),
                    "rms_el_deg": float(rms[1]), "dx_cm": (100 * np.asarray(fits["pose"]["c"][3:6])).tolist(),
                    "fits": fits})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("sessions", nargs="+")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--whiten", action="store_true", help="weight by each component's scatter, not sigma_deg")
    args = ap.parse_args(argv)
    rows = [r for s in args.sessions for r in session(args.work, s, weighted=not args.whiten)]
    models = [m for m in NESTED if any(m in r["fits"] for r in rows)]
    print("session      array n  |uz|  az° el° | explained (F) per model | pose δx cm (array frame)")
    for r in rows:
        f = r["fits"]
        print(f"{r['session']:12s} {r['array']}{'R' if r['ref'] else ' '} {r['n']:3d} {r['uz_med']:.2f} "
              f"{r['rms_az_deg']:.2f} {r['rms_el_deg']:.2f} | " + " ".join(
                  f"{m} {f[m]['explained']:.2f} ({f[m]['F']:.1f})" for m in models if m in f)
              + f" | {np.round(r['dx_cm'], 1)} k {f['rot+k']['c'][3]:+.4f}")
    frame = pd.DataFrame(rows)
    for preset, d in frame.groupby(frame["session"].str.rsplit("_", n=1).str[0]):
        print(f"{preset:8s} {len(d):3d} arrays | " + " ".join(
            f"{m} p<0.01 {np.mean([x[m]['p_value'] < 0.01 for x in d.fits if m in x]):.2f}"
            for m in models if any(m in x for x in d.fits)))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
