"""Room simulator benchmark (issues #3, #9, #12): wall time, peak memory and timing accuracy.

    python benchmarks/bench_roomsim.py            # all cases (several minutes on 2 cores)
    python benchmarks/bench_roomsim.py --quick    # the acceptance case only
    python benchmarks/bench_roomsim.py --realistic [--long N]   # lab, hall, hard + an N-event lab session

Realistic presets (issue #9): each case runs in its own process, which reports its wall time and peak
resident memory (``ru_maxrss``); the long session repeats the lab's speaker loop to N events (1.5 s apart)
to show that memory does not grow with the session length (recordings are streamed to the WAVs).

Speed: `simulate` wall time (image sources + RIRs + convolutions + noise + writing) per case; the target
is ≤ 60 s for 5 arrays × 6 mics × 14 events at 16 kHz with RT60 0.3 s (paper-traj3 defaults).
Accuracy: for anechoic, noise-free scenes with drifts up to 5e-4, every chirp at every mic is timed by a
matched filter with a continuous lag (template = the published chirp on the array's drifting clock) and
compared with the analytic clock model; the same with RT60 0.3 s shows how much early reflections bias a
plain matched filter (a property of the room, not a simulator error).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf
from scipy.optimize import minimize_scalar


from calib.pipeline.simulate import roomsim as rs

INF = float("inf")


def timing_errors(sc, d):
    """Matched-filter arrival (local) minus the analytic model, for every array × event × mic (s)."""
    ch = sc["chirp"]
    fs = sc["fs"]
    model = rs.arrival_times(sc, mics=True)
    errs = []
    for a, t in zip(sc["arrays"], model):
        y, _ = sf.read(d / f"{a['name']}.wav", always_2d=True)
        rate = fs / (1 + a["drift"])
        for j in range(t.shape[0]):
            for m in range(t.shape[1]):
                n = np.arange(int((t[j, m] - 0.01) * fs), int((t[j, m] + ch["duration"] * 1.01 + 0.01) * fs))
                seg = y[n, m]

                def neg(tc):
                    u = (n / fs - tc) * rate / fs
                    return -np.dot(seg, rs.chirp_signal(u, ch))
                # search ±3 samples around the model: wide enough to expose any sample-level error
                r = minimize_scalar(neg, bounds=(t[j, m] - 3 / fs, t[j, m] + 3 / fs), method="bounded",
                                    options={"xatol": 1e-11})
                errs.append(r.x - t[j, m])
    return np.array(errs)


def run_case(preset, fs, rt60, tmp, accuracy=False, **kw):
    sc = rs.make_scenario(preset, seed=0, fs=fs, rt60=rt60, **kw)
    v = rs.validate_scenario(sc)
    e_abs, order = rs._room_acoustics(v)
    t0 = time.perf_counter()
    d = rs.simulate(sc, Path(tmp) / f"{preset}-{fs}-{rt60}-{len(kw)}", overwrite=True)
    wall = time.perf_counter() - t0
    n = sf.info(d / "A1.wav").frames
    row = {"preset": preset, "fs": fs, "rt60": rt60,
           "arrays x mics": f"{len(v['arrays'])}x{len(v['arrays'][0]['mics'])}",
           "events": len(v["sources"]), "max_order": order, "audio_s": n / fs, "wall_s": wall,
           "MB": sum(p.stat().st_size for p in d.rglob("*") if p.is_file()) / 1e6}
    if accuracy:
        err = timing_errors(sc, d)
        row["max_err_ns"] = np.max(np.abs(err)) * 1e9
        row["rms_err_ns"] = np.sqrt(np.mean(err ** 2)) * 1e9
    return row


def realistic_case(preset, n_events, tmp):
    """Simulate one realistic case in this process; a table row with wall time and peak memory."""
    import resource

    sc = rs.make_scenario(preset, seed=0)
    if n_events > len(sc["sources"]):           # long session: the speaker keeps flying the same loop
        reps = -(-n_events // len(sc["sources"]))
        sc["sources"] = (sc["sources"] * reps)[:n_events]
        sc["t_emit"] = (sc["t_emit"][0] + 1.5 * np.arange(n_events)).round(6).tolist()
        sc["event_level_db"] = None
        sc["interferers"] = []
    t0 = time.perf_counter()
    d = rs.simulate(sc, Path(tmp) / f"{preset}-{n_events}", overwrite=True)
    wall = time.perf_counter() - t0
    v = rs.validate_scenario(sc)
    n = sf.info(d / "A1.wav").frames
    return {"preset": preset, "fs": v["fs"], "rt60": v["rt60"],
            "arrays x mics": f"{len(v['arrays'])}x{len(v['arrays'][0]['mics'])}", "events": len(v["sources"]),
            "audio_s": n / v["fs"], "MB": sum(p.stat().st_size for p in d.rglob("*") if p.is_file()) / 1e6,
            "wall_s": wall, "peak_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "float64_session_MB": sum(sf.info(d / f"{a['name']}.wav").frames * len(a["mics"]) * 8
                                      for a in v["arrays"]) / 1e6}


def run_realistic(long_events):
    import json
    import subprocess

    rows = []
    for preset, n in [("lab", 14), ("hall", 14), ("hard", 14), ("lab", long_events)]:
        out = subprocess.run([sys.executable, __file__, "--case", preset, str(n)], capture_output=True, text=True,
                             check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(f"  {preset} {n} events: {rows[-1]['wall_s']:.1f} s", file=sys.stderr)
    return rows, ["preset", "fs", "rt60", "arrays x mics", "events", "audio_s", "MB", "wall_s", "peak_MB",
                  "float64_session_MB"]


def print_table(rows, cols):
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{r.get(c, ''):.3g}" if isinstance(r.get(c), float) else str(r.get(c, ""))
                                for c in cols) + " |")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="only the acceptance speed case")
    ap.add_argument("--realistic", action="store_true", help="the realistic presets and a long session")
    ap.add_argument("--long", type=int, default=240, help="events of the long lab session [240]")
    ap.add_argument("--case", nargs=2, help=argparse.SUPPRESS)    # internal: one realistic case, JSON row
    args = ap.parse_args()
    if args.case:
        import json

        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(realistic_case(args.case[0], int(args.case[1]), tmp)))
        return
    if args.realistic:
        rows, cols = run_realistic(args.long)
        print_table(rows, cols)
        print(f"\npeak_MB = ru_maxrss of the process that ran the case (imports included); float64_session_MB = "
              "what holding every recording in float64 would take.")
        return
    cases = [("paper-traj3", 16000, 0.3, False, {})]
    if not args.quick:
        cases += [
            ("paper-traj1", 16000, 0.3, False, {}),
            ("paper-traj2", 16000, 0.3, False, {}),
            ("lab3", 16000, 0.3, False, {}),
            ("paper-traj3", 16000, 0.6, False, {}),
            ("paper-traj3", 48000, 0.3, False, {}),
            ("paper-traj3", 16000, 0.0, True, {"snr": INF, "drift_max": 5e-4}),
            ("paper-traj3", 48000, 0.0, True, {"snr": INF, "drift_max": 5e-4}),
            ("lab3", 16000, 0.0, True, {"snr": INF, "drift_max": 5e-4}),
            ("lab3", 16000, 0.3, True, {"snr": INF, "drift_max": 5e-4}),
        ]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset, fs, rt60, acc, kw in cases:
            rows.append(run_case(preset, fs, rt60, tmp, accuracy=acc, **kw))
            r = rows[-1]
            print(f"  {preset} fs={fs} rt60={rt60}: {r['wall_s']:.1f} s", file=sys.stderr)
    cols = ["preset", "fs", "rt60", "arrays x mics", "events", "max_order", "audio_s", "MB", "wall_s",
            "max_err_ns", "rms_err_ns"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            cells.append(f"{v:.3g}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")
    import os
    print(f"\n{os.cpu_count()} CPUs; wall_s = pipeline.simulate.roomsim.simulate() including writing the session.")


if __name__ == "__main__":
    main()
