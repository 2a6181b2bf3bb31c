"""Frontend scale benchmark: `calib features` (pipeline.features.session_features) vs recording duration.

    python benchmarks/bench_features_scale.py                       # 14, 60, 240, 960 events at 16 and 48 kHz
    python benchmarks/bench_features_scale.py --events 14 60 --rates 16000
    python benchmarks/bench_features_scale.py --plot docs/img/features_scale.png
    python benchmarks/bench_features_scale.py --events 960 --rates 48000 --jobs 2   # 2 arrays at a time
    python benchmarks/bench_features_scale.py --association   # association alone, 240 … 16000 events
    python benchmarks/bench_features_scale.py --json r.json; ... --replot r.json --plot out.png
    python benchmarks/bench_features_scale.py --cli --events 90 --rates 48000   # `calib features` as a process (3 min)
    python benchmarks/bench_features_scale.py --cli --events 3600 --rates 48000 --arrays 8 --mics 2   # 2 hours, 11 GB

Sessions: anechoic and synthetic, written block by block (so writing them is cheap and bounded in memory;
the room simulator is not needed to measure the frontend's cost): 5 arrays × 6 mics (a 3.54 cm circle,
mics alternately 2 cm above and below its plane) at the corners and the middle of a 12 × 9 m floor, one
chirp of 0.5 s, 500–4000 Hz every 2 ± 0.3 s from a robot driving a loop at 0.3 m height, clock offsets up
to 1 s and drifts up to 1e-4, white noise 30 dB below a chirp at 1 m, 16-bit PCM. Every mic's signal is
the sweep (frontend.signals.sweep) evaluated at its exact, drifted arrival times, so no fractional-delay
filter stands between the truth and the audio.

Each case runs in a fresh child process (the parent's imports and data do not count): wall time and CPU
time (user + system, all threads) of session_features, each also as % of the recording's duration (the
CPU figure is what the machine's load does not inflate), and the child's peak resident memory (ru_maxrss). Also checked against the truth: events
matched / present, spurious detections, and the RMS error of TDOA-S (µs; the drift bias β δ cancels in a
difference of two arrivals on one clock). Sessions are kept in --dir and reused.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf

from calib.frontend.signals import sweep

C = 343.0
CHIRP = {"f0": 500.0, "f1": 4000.0, "duration": 0.5, "fade": 0.005}
MICS = np.c_[0.0354 * np.cos(np.arange(6) * np.pi / 3), 0.0354 * np.sin(np.arange(6) * np.pi / 3),
             0.02 * (-1.0) ** np.arange(6)]
ARRAY_POS = np.array([[0.5, 0.5, 2.5], [11.5, 0.5, 2.4], [11.5, 8.5, 2.6], [0.5, 8.5, 2.5], [6.0, 4.5, 2.8],
                      [6.0, 0.5, 2.6], [6.0, 8.5, 2.4], [11.5, 4.5, 2.7]])   # the first 5 unless --arrays
MIC_ORDER = [0, 3, 1, 4, 2, 5]  # --mics M keeps the first M of these (2: a 7.1 cm pair across the circle)
SPACING, JITTER = 2.0, 0.3     # s between chirps
NOISE_RMS = 10 ** (-30 / 20) / np.sqrt(2)  # 30 dB below a unit-amplitude sweep (rms 1/√2) at 1 m
BLOCK_S = 10.0                 # the writer renders this many seconds at a time


def scene(n_events, seed=0, n_arrays=5):
    """Emission times, source positions and clocks (offset τ, drift δ) of a synthetic session."""
    rng = np.random.default_rng(seed)
    t_emit = 1.0 + np.cumsum(np.r_[0.0, SPACING + rng.uniform(-JITTER, JITTER, n_events - 1)])
    ang = 2 * np.pi * np.arange(n_events) / 40.0
    src = np.c_[6.0 + 4.0 * np.cos(ang), 4.5 + 3.0 * np.sin(ang), np.full(n_events, 0.3)]
    tau = rng.uniform(0.0, 1.0, n_arrays)
    delta = rng.uniform(-1e-4, 1e-4, n_arrays)
    return t_emit, src, tau, delta


def write_session(folder, n_events, fs, seed=0, n_arrays=5, n_mics=6):
    """Write session.toml, events.csv and one 16-bit WAV per array (rendered BLOCK_S at a time); ``n_arrays``
    (≤ 8) of :data:`ARRAY_POS`, ``n_mics`` (≤ 6) of :data:`MICS` in :data:`MIC_ORDER`."""
    folder.mkdir(parents=True, exist_ok=True)
    t_emit, src, tau, delta = scene(n_events, seed, n_arrays)
    mics = MICS[MIC_ORDER[:n_mics]]
    rng = np.random.default_rng(seed + 1)
    n_t = int(np.ceil(CHIRP["duration"] * fs))
    lines = ["speed_of_sound = 343.0", 'reference_array = "A1"', "", "[chirp]",
             *(f"{k} = {v}" for k, v in CHIRP.items()), ""]
    for i, pos in enumerate(ARRAY_POS[:n_arrays]):
        name = f"A{i + 1}"
        lines += ["[[arrays]]", f'name = "{name}"', f'wav = "{name}.wav"',
                  "mics = [" + ", ".join("[" + ", ".join(f"{v:.6f}" for v in m) + "]" for m in mics) + "]", ""]
        mic_pos = pos + mics
        dist = np.linalg.norm(src[:, None, :] - mic_pos[None], axis=-1)  # (K, M)
        t_arr = (1 + delta[i]) * (t_emit[:, None] + dist / C) + tau[i]  # local seconds
        n_total = int((t_arr.max() + 1.0) * fs)
        with sf.SoundFile(folder / f"{name}.wav", "w", fs, len(mics), "PCM_16") as f:
            for b0 in range(0, n_total, int(BLOCK_S * fs)):
                b1 = min(b0 + int(BLOCK_S * fs), n_total)
                blk = rng.standard_normal((b1 - b0, len(mics)), np.float32) * np.float32(NOISE_RMS)
                near = np.flatnonzero((t_arr.max(axis=1) * fs > b0 - n_t - 2) & (t_arr.min(axis=1) * fs < b1))
                for k in near:
                    for m in range(len(mics)):
                        n0 = max(b0, int(t_arr[k, m] * fs))
                        n1 = min(b1, int(t_arr[k, m] * fs) + n_t + 2)
                        u = (np.arange(n0, n1) / fs - t_arr[k, m]) / (1 + delta[i])  # emitter seconds
                        blk[n0 - b0 : n1 - b0, m] += (sweep(u, CHIRP["f0"], CHIRP["f1"], CHIRP["duration"],
                                                            CHIRP["fade"]) / dist[k, m]).astype(np.float32)
                f.write(np.clip(blk, -1, 1))
    (folder / "session.toml").write_text("\n".join(lines))
    pd.DataFrame({"event": np.arange(n_events), "t_emit": t_emit, "odom_x": src[:, 0], "odom_y": src[:, 1],
                  "odom_z": src[:, 2]}).to_csv(folder / "events.csv", index=False, float_format="%.9f")
    (folder / "complete").write_text("ok\n")


def truth_tdoa_s(n_events, seed=0):
    """True TDOA-S per array between consecutive events: (1 + δ) × difference of arrivals at the origin."""
    t_emit, src, tau, delta = scene(n_events, seed)
    out = {}
    for i, pos in enumerate(ARRAY_POS[: len(delta)]):
        a = t_emit + np.linalg.norm(src - pos, axis=1) / C
        out[f"A{i + 1}"] = {(j, j + 1): (1 + delta[i]) * (a[j + 1] - a[j]) for j in range(n_events - 1)}
    return out


CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from calib.pipeline.features import session_features
t1 = time.perf_counter()
cpu0 = sum(resource.getrusage(resource.RUSAGE_SELF)[:2])
feats, diag = session_features(sys.argv[1], jobs=int(sys.argv[3]))
t2 = time.perf_counter()
feats["tdoa_s"].to_csv(sys.argv[2], index=False)
arr = diag["arrays"]
ru = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"import_s": t1 - t0, "features_s": t2 - t1, "peak_rss_mb": ru.ru_maxrss / 1024,
    "cpu_s": ru.ru_utime + ru.ru_stime - cpu0, "duration_s": diag["recording_duration_s"],
    "matched": sum(a["association"]["n_matched"] for a in arr.values()),
    "spurious": sum(len(a["spurious"]) for a in arr.values()),
    "timings": {k: sum(a["timings_s"].get(k, 0.0) for a in arr.values()) for k in
                ("read", "detect", "associate", "timing", "doa")}}))
"""


def run_case(folder, n_events, seed, jobs=1):
    """session_features on ``folder`` in a child process (``jobs`` arrays at a time). Returns a dict of
    measurements."""
    csv = folder / "tdoa_s.csv"
    p = subprocess.run([sys.executable, "-c", CHILD, str(folder), str(csv), str(jobs)], capture_output=True,
                       text=True)
    if p.returncode:
        raise RuntimeError(p.stderr)
    r = json.loads(p.stdout.strip().splitlines()[-1])
    ts = pd.read_csv(csv)
    truth = truth_tdoa_s(n_events, seed)
    err = [row.tdoa - truth[row.array][(row.from_event, row.to_event)] for row in ts.itertuples()
           if (row.from_event, row.to_event) in truth[row.array]]
    r["tdoa_s_rms_us"] = float(np.sqrt(np.mean(np.square(err))) * 1e6) if err else float("nan")
    r["present"] = n_events * len(ARRAY_POS)
    return r


def association_table(sizes=(240, 960, 2000, 4000, 8000, 16000), seed=0):
    """CPU time of frontend.associate on synthetic detections: drift up to 1e-3, offsets of seconds, 30 ms
    of propagation jitter, 5 % of events lost, 10 % spurious detections (≥ 0.3 s from any arrival)."""
    from calib.frontend.associate import associate

    print("| events | detections | CPU (s) | µs per event | all assigned right |")
    print("|---|---|---|---|---|")
    for k in sizes:
        rng = np.random.default_rng(seed + k)
        t_emit = np.cumsum(np.r_[rng.uniform(0, 5), rng.uniform(1.5, 3.5, k - 1)])
        drift, offset = rng.uniform(-1e-3, 1e-3), rng.uniform(-20, 20)
        arr = offset + (1 + drift) * (t_emit - t_emit[0] + rng.uniform(0, 0.03, k))
        keep = rng.random(k) > 0.05
        spur = rng.uniform(arr.min() - 2, arr.max() + 2, k // 10)
        p = np.clip(np.searchsorted(arr, spur), 1, k - 1)
        spur = spur[np.minimum(np.abs(spur - arr[p - 1]), np.abs(spur - arr[p])) > 0.3]
        det = np.r_[arr[keep], spur]
        score = np.r_[rng.uniform(20, 100, keep.sum()), rng.uniform(10, 200, len(spur))]
        truth = np.r_[np.flatnonzero(keep), np.full(len(spur), -1)]
        t0 = time.process_time()
        res = associate(det, score, t_emit)
        cpu = time.process_time() - t0
        print(f"| {k} | {len(det)} | {cpu:.3f} | {1e6 * cpu / k:.0f} | {bool(np.all(res['event_of'] == truth))} |")


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for fs in sorted({r["fs"] for r in rows}):
        rr = sorted((r for r in rows if r["fs"] == fs), key=lambda r: r["duration_s"])
        d = [r["duration_s"] for r in rr]
        line, = ax[0].loglog(d, [r["features_s"] for r in rr], "o-", label=f"{fs // 1000} kHz wall")
        ax[0].loglog(d, [r["cpu_s"] for r in rr], "s:", color=line.get_color(), label=f"{fs // 1000} kHz CPU")
        ax[1].semilogx(d, [r["peak_rss_mb"] for r in rr], "o-", label=f"{fs // 1000} kHz")
    d = np.array([min(r["duration_s"] for r in rows), max(r["duration_s"] for r in rows)])
    ax[0].loglog(d, 0.01 * d, "k--", lw=1, label="1 % of the audio")
    ax[0].set(xlabel="recording duration (s)", ylabel="calib features time (s)",
              title="time (wall depends on the machine's load)")
    ax[1].axhline(1024, color="k", ls="--", lw=1, label="1 GB")
    ax[1].set(xlabel="recording duration (s)", ylabel="peak RSS (MB)", title="peak memory", ylim=(0, None))
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(f"calib features: 5 arrays × {len(MICS)} mics, a chirp every ~{SPACING:g} s")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def cli_case(folder, jobs):
    """``calib features FOLDER -o OUT -q`` as its own process (start-up, imports, reading, writing the features
    and diagnostics included): wall, user + system CPU and peak RSS of that process (dict)."""
    import tempfile

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from cliproc import calib_cmd, measure

    with tempfile.TemporaryDirectory(prefix="calib-bench-features-") as tmp:
        m = measure(calib_cmd("features", folder, "-o", Path(tmp) / "features", "--diagnostics",
                              Path(tmp) / "diagnostics", "--jobs", jobs, "-q"))
        if m["rc"]:
            raise RuntimeError(m["stderr"])
        duration = json.loads((Path(tmp) / "diagnostics" / "diagnostics.json").read_text())["recording_duration_s"]
    return {**m, "duration_s": duration}


def session_name(k, fs, args):
    """The --dir folder of a session (the default layout keeps the names of earlier runs)."""
    layout = "" if (args.arrays, args.mics) == (5, 6) else f"_a{args.arrays}m{args.mics}"
    return f"k{k}_fs{fs}_s{args.seed}{layout}"


def main_cli(args):
    """The --cli table: one row per session, the whole `calib features` process."""
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f} (1/5/15 min); "
          f"calib features --jobs {args.jobs} as a process")
    print("| events | fs | audio (s) | wall (s) | wall % of audio | CPU (s) | CPU % of audio | peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|---|")
    for fs in args.rates:
        for k in args.events:
            folder = args.dir / session_name(k, fs, args)
            if not (folder / "complete").exists():
                write_session(folder, k, fs, args.seed, args.arrays, args.mics)
            r = cli_case(folder, args.jobs)
            d = r["duration_s"]
            print(f"| {k} | {fs // 1000} kHz | {d:.0f} | {r['wall_s']:.2f} | {100 * r['wall_s'] / d:.2f} | "
                  f"{r['cpu_s']:.2f} | {100 * r['cpu_s'] / d:.2f} | {r['peak_mb']:.0f} |", flush=True)
    print(f"load after: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, nargs="+", default=[14, 60, 240, 960])
    ap.add_argument("--rates", type=int, nargs="+", default=[16000, 48000])
    ap.add_argument("--dir", type=Path, default=Path("/tmp/calib-bench-features-scale"))
    ap.add_argument("--plot", type=lambda s: Path(s) if s else None, default=Path("docs/img/features_scale.png"),
                    help='the figure to write ("" for none)')
    ap.add_argument("--json", type=Path, help="also write the raw numbers here")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arrays", type=int, default=5, choices=range(2, 9), help="arrays (--cli; default 5)")
    ap.add_argument("--mics", type=int, default=6, choices=range(2, 7), help="mics per array (--cli; default 6)")
    ap.add_argument("--jobs", type=int, default=1, help="arrays at a time (session_features(jobs=...), threads)")
    ap.add_argument("--association", action="store_true", help="only the association timing table")
    ap.add_argument("--replot", type=Path, help="only redraw --plot from a --json file of an earlier run")
    ap.add_argument("--cli", action="store_true", help="time `calib features` as a process (its default --jobs "
                                                       "unless --jobs is given)")
    args = ap.parse_args()
    if args.cli:
        args.jobs = args.jobs if "--jobs" in sys.argv else -1
        return main_cli(args)
    if args.replot:
        plot(json.loads(args.replot.read_text()), args.plot)
        return
    if args.association:
        association_table(seed=args.seed)
        return
    rows = []
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f} (1/5/15 min); "
          f"jobs {args.jobs}")
    print("| events | fs | audio (s) | write (s) | features (s) | wall % of audio | CPU (s) | CPU % of audio | peak RSS (MB)"
          " | matched | spurious | TDOA-S RMS (µs) | detect / associate / timing / doa (s, wall) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for fs in args.rates:
        for k in args.events:
            folder = args.dir / f"k{k}_fs{fs}_s{args.seed}"
            t0 = time.perf_counter()
            if not (folder / "complete").exists():
                write_session(folder, k, fs, args.seed)
            t_write = time.perf_counter() - t0
            r = run_case(folder, k, args.seed, args.jobs)
            r.update(events=k, fs=fs, write_s=t_write)
            rows.append(r)
            t = r["timings"]
            print(f"| {k} | {fs // 1000} kHz | {r['duration_s']:.0f} | {t_write:.1f} | {r['features_s']:.2f} | "
                  f"{100 * r['features_s'] / r['duration_s']:.2f} | {r['cpu_s']:.2f} | "
                  f"{100 * r['cpu_s'] / r['duration_s']:.2f} | {r['peak_rss_mb']:.0f} | "
                  f"{r['matched']}/{r['present']} | {r['spurious']} | {r['tdoa_s_rms_us']:.2f} | "
                  f"{t['detect']:.1f} / {t['associate']:.2f} / {t['timing']:.1f} / {t['doa']:.1f} |", flush=True)
    print(f"load after: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    if args.plot:
        plot(rows, args.plot)
        print(f"plot: {args.plot}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
