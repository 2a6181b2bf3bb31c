"""Wall and CPU time of `calib features` (session_features) with one thread and with --jobs threads.

    python benchmarks/bench_features_jobs.py SESSION [SESSION ...] [--jobs 2] [--repeat 4]
    python benchmarks/bench_features_jobs.py SESSION [SESSION ...] --one-shot [--repeat 5]

Per session: jobs=1 and jobs=N alternating in one process, the fastest of --repeat runs of each, as % of
the recording's duration (its longest WAV). Also checks that both give the same features, bit for bit.
Wall time depends on the machine's load; the CPU column on it much less.

--one-shot: what `calib features` sees. Each run is a fresh process that extracts once (nothing cached,
no memory to reuse; imports not timed) with the default threads; median and worst of --repeat runs.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
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


TARGET_PERCENT = 2.0  # issue 9: feature extraction within 2 % of the recording's duration

# one fresh extraction: prints wall and CPU seconds (argv: session)
ONE_SHOT = """
import sys, time
from pathlib import Path
from calib.pipeline.features import session_features
w, c = time.perf_counter(), time.process_time()
session_features(Path(sys.argv[1]), jobs=-1)
print(time.perf_counter() - w, time.process_time() - c)
"""


def duration(session):
    return max(sf.info(w).duration for w in session.glob("*.wav") if w.name != "chirp.wav")


def one_shot(sessions, repeat):
    """Table of fresh-process extractions."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    rows = []
    for s in sessions:
        dur, runs = duration(s), {"1": []}
        for _ in range(repeat):
            for mode in runs:
                out = subprocess.run([sys.executable, "-c", ONE_SHOT, str(s), mode], env=env, check=True,
                                     capture_output=True, text=True).stdout.split()
                runs[mode].append([100 * float(v) / dur for v in out])
        row = {"session": s.name, "audio_s": round(dur, 1)}
        for mode, tag in (("1", "cli"),):
            wall, cpu = [r[0] for r in runs[mode]], [r[1] for r in runs[mode]]
            row |= {f"wall_%_{tag}_med": statistics.median(wall), f"wall_%_{tag}_max": max(wall),
                    f"cpu_%_{tag}_med": statistics.median(cpu)}
            if tag == "cli":  # issue 9's target, run by run
                row["cli_runs_<=2%"] = f"{sum(w <= TARGET_PERCENT for w in wall)}/{len(wall)}"
        rows.append(row)
        print(pd.DataFrame(rows[-1:]).to_string(index=False, float_format="%.2f"), flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=4)
    ap.add_argument("--one-shot", action="store_true", help="fresh processes, default threads (see above)")
    args = ap.parse_args()
    print(f"load: {' '.join(f'{v:.2f}' for v in os.getloadavg())} (1/5/15 min)")
    if args.one_shot:
        print(pd.DataFrame(one_shot(args.sessions, args.repeat)).to_string(index=False, float_format="%.2f"))
        print(f"load after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
        return
    rows = []
    for s in args.sessions:
        dur = duration(s)
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
