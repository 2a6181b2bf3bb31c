"""Why the frontend's DOAs err more than doa.csv states (issue 27): one acoustic factor changed at a time.

    python benchmarks/diag_doa_bisect.py --seeds 350,351 --conds base,anechoic,quiet --work /tmp/bis

Each condition renders the stopped twin of ``moving`` SEED (``--preset``: another deployment preset) (the same scene with the speaker held at each sweep
start: the DOA errors are the same moving or stopped, docs/results.md) with one change, runs the frontend
(``session_features``) and compares every doa.csv row with the true direction (array frame). Rows are grouped by
the array's mount (``wall``: 10 cm off a wall, its mic plane tilted 0–30° from the wall's; ``table``: level)
and by the ``doa_reflection`` flag. Columns: rows, RMS error (deg), its in-plane / elevation parts (the angle
in the mic plane; the angle out of it), the median stated sigma_deg, and RMS(error / σ) with σ the row's
sigma_deg per tangent axis (error / (σ√2) for the 2-D angle; 1 = honest).

Conditions (``--conds``): base; anechoic (rt60 0: the direct path only); quiet (no sensor / diffuse noise, no
hum); nogain (no mic gain mismatch); omni (omni speaker); fs48 (48 kHz); wide (chirp 500–7000 Hz);
offwall (wall arrays moved 0.5 m into the room); ideal (anechoic + quiet + nogain: the estimator alone).
"""
from __future__ import annotations

import argparse
import copy
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_moving_arrivals import parse_seeds  # noqa: E402  (a sibling script's seed parser)

INF = float("inf")
CONDS = {
    "base": {},
    "anechoic": {"rt60": 0.0},
    "quiet": {"snr": INF, "diffuse_snr": INF, "hum_snr": INF},
    "nogain": {"gain_mismatch_db": 0.0},
    "omni": {"directivity": "omni"},
    "fs48": {"fs": 48000},
    "wide": {"chirp": {"f0": 500.0, "f1": 7000.0}},
    "offwall": {},
    "ideal": {"rt60": 0.0, "snr": INF, "diffuse_snr": INF, "hum_snr": INF, "gain_mismatch_db": 0.0},
}
OFF_WALL_M = 0.5


def _mount(a):
    """"wall" if the array's mic-plane normal is nearly horizontal, "table" if vertical, the board's name for
    3-D boards (tetrahedra) and the others (stands: any rotation)."""
    from calib.geometry import mic_geometry
    kind, normal = mic_geometry(np.asarray(a["mics"], float))
    if kind != "planar" or a.get("doa_hemisphere") is None:
        return f"{kind}"
    n = np.asarray(a["R"] if "R" in a else _rot(a)) @ normal
    return "wall" if abs(n[2]) < 0.7 else "table"


def _rot(a):
    from scipy.spatial.transform import Rotation
    q = np.asarray(a["quat"], float)
    return Rotation.from_quat(q, scalar_first=True).as_matrix()


PRESET = "moving"   # --preset: a deployment preset with wall and table mounts


def scenario(seed, cond):
    from calib.pipeline.simulate.roomsim import make_scenario

    over = copy.deepcopy(CONDS[cond])
    sc = make_scenario(PRESET, seed, **over)
    sc = {k: v for k, v in sc.items() if k != "trajectory"}   # the stopped twin: sources = the sweep starts
    if "fs" in over:   # the boards state their own rate
        for a in sc["arrays"]:
            a["fs"] = over["fs"]
    if cond == "offwall":
        for a in sc["arrays"]:
            n = _rot(a)[:, 2]
            if abs(n[2]) < 0.7:
                h = np.r_[n[:2], 0.0] / np.linalg.norm(n[:2])
                a["position"] = (np.asarray(a["position"]) + OFF_WALL_M * h).tolist()
    return sc


def features(seed, cond, work, **options):
    from calib.pipeline.features import session_features
    from calib.pipeline.simulate.roomsim import simulate

    folder = work / f"{PRESET}_{seed}_{cond}"
    sc = scenario(seed, cond)
    if not (folder / "session.toml").exists():
        t0 = time.time()
        simulate(sc, folder)
        print(f"  rendered {folder.name} in {time.time() - t0:.0f} s", file=sys.stderr)
    tag = "_".join(f"{k}{v}" for k, v in sorted(options.items()))
    cache = folder / f"features{tag}.pkl"
    if cache.exists():
        return sc, pickle.loads(cache.read_bytes())
    t0 = time.time()
    feats, _ = session_features(folder, **options)
    print(f"  features {folder.name} {tag} in {time.time() - t0:.0f} s", file=sys.stderr)
    cache.write_bytes(pickle.dumps(feats))
    return sc, feats


def row_errors(sc, feats):
    """One row per doa.csv row: array, mount, flag, error (deg), in-plane / elevation errors, sigma_deg."""
    from calib.pipeline.simulate.scenario import validate_scenario

    vs = validate_scenario(sc)
    src = np.asarray(vs["sources"], float)
    ev = {e: j for j, e in enumerate(feats["events"]["event"])}
    arrays = {a["name"]: a for a in vs["arrays"]}
    out = []
    for r in feats["doa"].itertuples():
        a = arrays[r.array]
        R = np.asarray(a["R"])
        centre = np.asarray(a["position"]) + R @ np.mean(np.asarray(a["mics"], float), axis=0)
        t = (src[ev[r.event]] - centre) @ R
        t /= np.linalg.norm(t)
        u = np.array([r.ux, r.uy, r.uz])
        err = np.degrees(np.arccos(np.clip(u @ t, -1, 1)))
        el_t, el_u = np.degrees(np.arcsin(np.clip(t[2], -1, 1))), np.degrees(np.arcsin(np.clip(u[2], -1, 1)))
        az = np.degrees(np.angle(np.exp(1j * (np.arctan2(u[1], u[0]) - np.arctan2(t[1], t[0])))))
        out.append({"array": r.array, "mount": _mount(a), "refl": "doa_reflection" in str(r.flag),
                    "flag": str(r.flag), "err": err, "az": az * np.cos(np.radians(el_t)), "el": el_u - el_t,
                    "elev": el_t, "sigma": r.sigma_deg, "quality": r.quality})
    return pd.DataFrame(out)


def summary(df):
    rows = []
    for (mount, refl), d in df.groupby(["mount", "refl"]):
        z = d["err"] / (np.sqrt(2) * d["sigma"])
        rows.append({"mount": mount, "refl": refl, "n": len(d), "rms": np.sqrt(np.mean(d["err"] ** 2)),
                     "az_rms": np.sqrt(np.mean(d["az"] ** 2)), "el_mean": d["el"].mean(),
                     "el_rms": np.sqrt(np.mean(d["el"] ** 2)), "sigma_med": d["sigma"].median(),
                     "err/σ": np.sqrt(np.nanmean(z**2))})
    return pd.DataFrame(rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="350")
    ap.add_argument("--conds", default="base")
    ap.add_argument("--work", type=Path, default=Path("/tmp/doa_bisect"))
    ap.add_argument("--gate-pulses", type=float, default=None)
    ap.add_argument("--preset", default="moving")
    ap.add_argument("--dump", type=Path, default=None, help="write every row's errors here (csv)")
    args = ap.parse_args(argv)
    global PRESET
    PRESET = args.preset
    args.work.mkdir(parents=True, exist_ok=True)
    opts = {} if args.gate_pulses is None else {"gate_pulses": args.gate_pulses}
    pd.set_option("display.width", 200)
    allrows = []
    for cond in args.conds.split(","):
        dfs = []
        for seed in parse_seeds(args.seeds):
            sc, feats = features(seed, cond, args.work, **opts)
            d = row_errors(sc, feats)
            d["seed"], d["cond"] = seed, cond
            dfs.append(d)
        df = pd.concat(dfs)
        allrows.append(df)
        s = summary(df)
        s.insert(0, "cond", cond)
        print(s.to_string(index=False, float_format=lambda v: f"{v:.2f}"), flush=True)
    if args.dump:
        pd.concat(allrows).to_csv(args.dump, index=False)


if __name__ == "__main__":
    main()
