"""Wall and CPU time of `calib features` (session_features) with one thread and with --jobs threads.

    python benchmarks/bench_features_jobs.py SESSION [SESSION ...] [--jobs 2] [--repeat 4]

Per session: jobs=1 and jobs=N alternating in one process, the fastest of --repeat runs of each, as % of
the recording's duration (its longest WAV). Also checks that both give the same features, bit for bit.
Wall time depends on the machine's load; the CPU column on it much less.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import pandas as pd
import soundfile as sf

from calib.pipeline.features import session_features


def timed(session, jobs):
    t, c = time.perf_counter(), time.process_time()
    feats, _ = session_features(session, jobs=jobs)
    return time.perf_counter() - t, time.process_time() - c, feats


def same(a, b):
    return all(a[k].equals(b[k]) for k in ("events", "tdoa_m", "tdoa_s", "doa"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=4)
    args = ap.parse_args()
    print(f"load: {' '.join(f'{v:.2f}' for v in os.getloadavg())} (1/5/15 min)")
    rows = []
    for s in args.sessions:
        dur = max(sf.info(w).duration for w in s.glob("*.wav") if w.name != "chirp.wav")
        best = {1: [float("inf")] * 2, args.jobs: [float("inf")] * 2}
        out = {}
        for _ in range(args.repeat):
            for j in best:
                w, c, out[j] = timed(s, j)
                best[j] = [min(best[j][0], w), min(best[j][1], c)]
        rows.append({"session": s.name, "audio_s": round(dur, 1),
                     "wall_%_1": 100 * best[1][0] / dur, "cpu_%_1": 100 * best[1][1] / dur,
                     f"wall_%_{args.jobs}": 100 * best[args.jobs][0] / dur,
                     f"cpu_%_{args.jobs}": 100 * best[args.jobs][1] / dur,
                     "identical": same(out[1], out[args.jobs])})
        print(pd.DataFrame(rows[-1:]).to_string(index=False, float_format="%.2f"), flush=True)
    print(pd.DataFrame(rows).to_string(index=False, float_format="%.2f"))
    print(f"load after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
