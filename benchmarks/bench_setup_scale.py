"""A wrong mic geometry scale (issue 29): each array of simulated sessions declared `k` × too large or too small,
and the set-up consistency stage asked to name it (and nothing else); the clean sessions must raise nothing.

    python benchmarks/bench_setup_scale.py [--seeds 1 2 3] [--presets lab3 lab mixed office noisy] [--factors 1.3 2 0.7]

Prints one row per (preset, seed, array, factor): the board kind, the finding's check (or MISS), the other
findings; then the catch rate per board kind and factor, and the clean sessions' findings (false alarms).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from calib.frontend.doa import mic_geometry
from calib.pipeline.formats.session import read_session
from calib.pipeline.setupcheck import folder_findings
from calib.pipeline.simulate.roomsim import make_scenario, simulate

# label → (preset, overrides): small sessions; "noisy": the lab3 room at 10 dB SNR and RT60 0.6 s
SIZES = {"lab3": ("lab3", {"n_events": 10, "interval": 0.8, "chirp": {"duration": 0.2}}),
         "lab": ("lab", {"n_events": 10, "interval": 1.0, "chirp": {"duration": 0.2}}),
         "mixed": ("mixed", {"n_stops": 10}), "office": ("office", {"n_stops": 12}),
         "noisy": ("lab3", {"n_events": 10, "interval": 1.0, "chirp": {"duration": 0.2}, "snr": 10.0, "rt60": 0.6})}


def kind(mics):
    k, _ = mic_geometry(np.asarray(mics, float))
    return {"linear": "linear/pair", "planar": "planar", "volume": "3-D"}.get(k, k)


def findings(folder, target=None, factor=1.0):
    mics = {a["name"]: np.asarray(a["mics"], float) * factor for a in read_session(folder)["arrays"]
            if a["name"] == target}
    return folder_findings(folder, mics)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--presets", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--factors", type=float, nargs="+", default=[1.3, 2.0, 0.7])
    args = ap.parse_args()
    rows, clean = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            for seed in args.seeds:
                name, kw = SIZES[preset]
                d = simulate(make_scenario(name, seed, **kw), Path(tmp) / f"{preset}_{seed}")
                found = findings(d)
                clean.append((preset, seed, [f"{f.array}:{f.check}" for f in found]))
                print(f"{preset} seed {seed} clean: {clean[-1][2] or 'nothing'}", flush=True)
                for a in read_session(d)["arrays"]:
                    if len(a["mics"]) < 2:
                        continue
                    for k in args.factors:
                        t = time.perf_counter()
                        found = findings(d, a["name"], k)
                        hit = [f for f in found if f.array == a["name"] and f.status == "failed"]
                        rows.append((preset, seed, a["name"], kind(a["mics"]), k, hit[0].check if hit else "MISS",
                                     [f"{f.array}:{f.check}" for f in found if f not in hit]))
                        print(*rows[-1], f"{time.perf_counter() - t:.1f}s", flush=True)
    print("\ncatch rate by board kind and factor")
    for kd in sorted({r[3] for r in rows}):
        for k in args.factors:
            sel = [r for r in rows if r[3] == kd and r[4] == k]
            if sel:
                print(f"  {kd:12s} ×{k:<4g} {sum(r[5] != 'MISS' for r in sel)}/{len(sel)}")
    print(f"clean sessions with a finding: {sum(bool(c[2]) for c in clean)}/{len(clean)}")


if __name__ == "__main__":
    main()
