"""Red-team sweep for wrong answers that look right: `calib simulate` sessions under conditions beyond the
presets, `calib run` on each (the user's path, exit code kept), each array scored against truth.

    python benchmarks/bench_redteam.py CASES --work /tmp/redteam        # one case per line of CASES:
    #   NAME|PRESET|SEED|simulate options, e.g.
    #   c03|lab|602|--n-events 6
    #   c33|mixed|632|--set 'boards=["pair","circle6","linear4","tetra","circle7c"]' --clock A3=drop
    #   s1|lab|650|--set speed_of_sound=349.0 @c=343      # rendered at 349 m/s, session.toml then says 343
    #   o1|lab|652|@odo=1.03                              # events.csv odometry x, y scaled by 1.03 (wheel error)

Tokens ``@c=V`` (declare the speed of sound V in session.toml after rendering: a thermometer-less user) and
``@odo=S`` (scale the odometry's x, y: a wheel-diameter error) edit the rendered session. Sessions are reused
when present (delete the folder to render again). Per case: exit code, verdict, named arrays, and per array
its position / orientation error, the largest position error over its stated std (bench_deploy's scoring),
and the flags: (a) verdict ok with an array > 3σ off; (b) an array beyond the bound (3 cm / 1.5°; warehouse,
bighall 5 cm / 2°) that the verdict does not name; (c) an exit code other than 0/2/3, or anything on stderr.
A session with clock faults (truth/clocks.json) is scored against its true clocks too (``calib evaluate``'s
``clock`` block, :func:`clock_cells`): per true step found / in the right event interval / size within 3σ,
false steps, the drift model and the nominal-rate ratio recovered; flag (d) a true step not found, misplaced
or its size beyond 3σ; (e) a wrong rate (≥ 0.1 %) not reported as such; (f) a false step.
``--no-run`` rescores the runs already under ``--work`` (exit code then read from ``<run>/exit_code``);
``--rerun TAG`` runs `calib run` again into a copy ``<case>_TAG`` of each case's run, whose cached features
it reuses (the estimator and report stages run again: another software's before/after at a fraction of the CPU).
Seeds: use the development range for tuning; a held-out check uses its reserved seeds once.
"""
from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from bench_deploy import BOUND, WIDE  # noqa: E402

SIGMA_FLAG = 3.0   # (a): an array this many stated std off in an `ok` verdict
RATE_NAMED = 1e-3  # (e): a nominal-rate error this large is a wrong header, to be reported as one (issue 28)


def render(d, preset, seed, opts):
    """`calib simulate` (unless ``d`` holds a session), then the @c / @odo edits; '' or its error."""
    sim = [o for o in opts if not o.startswith("@")]
    edits = dict(o[1:].split("=", 1) for o in opts if o.startswith("@"))
    if not (d / "truth" / "manifest.json").is_file():
        p = subprocess.run([sys.executable, "-m", "calib", "simulate", "-o", str(d), "--preset", preset, "--seed",
                            str(seed), "--quiet", "--force", *sim], capture_output=True, text=True)
        if p.returncode:
            return f"simulate exit {p.returncode}: {p.stderr.strip()[-200:]}"
        if "c" in edits:
            toml = d / "session.toml"
            lines = [f"speed_of_sound = {float(edits['c'])}" if ln.startswith("speed_of_sound") else ln
                     for ln in toml.read_text().splitlines()]
            toml.write_text("\n".join(lines) + "\n")
        if "odo" in edits:
            ev = pd.read_csv(d / "events.csv")
            ev[["odom_x", "odom_y"]] *= float(edits["odo"])
            ev.to_csv(d / "events.csv", index=False, float_format="%.9f")
    return ""


def run(d, out, reuse, cached=None, more=()):
    """(exit code, stderr) of `calib run` on session ``d`` into ``out`` (kept in ``out/exit_code``), or with
    ``reuse`` those of the run already there; ``cached``: a run folder copied to ``out`` first (its features
    reused: no --force); ``more``: further `calib run` options."""
    if reuse:
        f = out / "exit_code"
        return (int(f.read_text()) if f.is_file() else "?"), ""
    if cached is not None and not out.exists():
        shutil.copytree(cached, out)
    force = [] if cached is not None else ["--force"]
    p = subprocess.run([sys.executable, "-m", "calib", "run", str(d), "-o", str(out), *force, "--quiet", *more],
                       capture_output=True, text=True)
    (out / "exit_code").write_text(f"{p.returncode}\n") if out.is_dir() else None
    return p.returncode, p.stderr


def score(d, out, preset):
    """(verdict, named, per-array rows [(array, cm, deg, σ-multiple or nan)], flags)."""
    v = json.loads((out / "calibration" / "report.json").read_text())["verdict"]
    named = set(v.get("flagged_arrays") or [])
    m = json.loads((out / "report" / "metrics.json").read_text())
    est = pd.read_csv(out / "calibration" / "arrays.csv").set_index("array")
    tru = pd.read_csv(d / "truth" / "arrays.csv").set_index("array")
    bound, rows, flags = WIDE.get(preset, BOUND), [], []
    for p in m["per_array"]:
        a = p["array"]
        cm = np.inf if p.get("position_m") is None else 100 * p["position_m"]
        deg = next((p[k] for k in ("geodesic_deg", "axis_deg") if p.get(k) is not None), 0.0)
        std = est.loc[a, ["x_std", "y_std", "z_std"]].to_numpy(float)
        err = est.loc[a, ["x", "y", "z"]].to_numpy(float) - tru.loc[a, ["x", "y", "z"]].to_numpy(float)
        z = float(np.max(np.abs(err) / std)) if np.all(np.isfinite(std) & (std > 0)) else np.nan
        rows.append((a, cm, deg, z))
        if (cm > 100 * bound[0] or deg > bound[1]) and a not in named:
            flags.append(f"(b) {a} off, unnamed")
        if v.get("status") == "ok" and z > SIGMA_FLAG:
            flags.append(f"(a) ok with {a} {z:.1f}σ")
    return v.get("status"), named, rows, flags


def clock_cells(out):
    """(text, flags) of a run's clock block against its truth (metrics.json ``clock``; ('', []) without faults)."""
    c = json.loads((out / "report" / "metrics.json").read_text()).get("clock")
    if not c:
        return "", []
    cells, flags = [], []
    for a in c["per_array"]:
        n = a["array"]
        for s in a["steps"]:
            z = s["size_error_sigma"]
            cells.append(f"{n} step {1e3 * s['size']:+g} ms ({s['after_event']}-{s['before_event']}): "
                         + ("missed" if not s["found"] else f"{'in' if s['placed'] else 'NOT in'} interval, "
                            f"{'nan' if z is None else f'{z:.1f}'}σ"))
            if not s["found"] or not s["placed"] or z is None or z > SIGMA_FLAG:
                flags.append(f"(d) {n} step {1e3 * s['size']:+g} ms " + ("missed" if not s["found"] else "wrong"))
        if a["false_steps"]:
            cells.append(f"{n} {a['false_steps']} false step(s)")
            flags.append(f"(f) {n} false step")
        if a["drift_model_true"] != "linear" or a["drift_model"] != "linear":
            cells.append(f"{n} drift {a['drift_model_true']} → {a['drift_model']}")
        rt, r = a["rate_ratio_true"], a["rate_ratio"]
        if abs(rt - 1.0) >= RATE_NAMED or r is not None:
            cells.append(f"{n} rate {rt:.5f} → {'-' if r is None else f'{r:.5f}'}")
            if abs(rt - 1.0) >= RATE_NAMED and (r is None or abs(r - rt) > 0.1 * abs(rt - 1.0)):
                flags.append(f"(e) {n} wrong rate not named")
    return "; ".join(cells), flags


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", type=Path, help="NAME|PRESET|SEED|OPTIONS per line (# comments)")
    ap.add_argument("--work", type=Path, required=True, help="sessions and runs (reused when present)")
    ap.add_argument("--run-args", default="", help="more `calib run` options, e.g. '--speed-of-sound fixed' (the "
                    "runs then go to NAME_run<--suffix>)")
    ap.add_argument("--suffix", default="", help="appended to each run folder's name")
    ap.add_argument("--no-run", action="store_true", help="rescore the runs already there")
    ap.add_argument("--rerun", metavar="TAG", help="run again into <case>_TAG, a copy of <case>_run (its features)")
    args = ap.parse_args()
    print("| case | preset:seed | options | exit | verdict | named | per array: cm / deg (σ-multiple), * named "
          "| clock block vs truth | flags |\n|---|---|---|---|---|---|---|---|---|")
    for line in args.cases.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, preset, seed, opts = (f.strip() for f in line.split("|", 3))
        d, out = args.work / name, args.work / f"{name}_run{args.suffix}"
        cached = args.work / f"{name}_run" if args.rerun else None
        if args.rerun:
            out = args.work / f"{name}_{args.rerun}"
            if not (cached / "features").is_dir():
                print(f"| {name} | {preset}:{seed} | `{opts}` | - | - | - | no run to reuse | - |", flush=True)
                continue
        err = render(d, preset, seed, shlex.split(opts))
        if err:
            print(f"| {name} | {preset}:{seed} | `{opts}` | - | - | - | {err} | simulate rejects |", flush=True)
            continue
        rc, stderr = run(d, out, args.no_run, cached, shlex.split(args.run_args))
        try:
            status, named, rows, flags = score(d, out, preset)
            clock, more = clock_cells(out)
            flags += more
        except (OSError, KeyError, ValueError) as exc:
            status, named, rows, flags, clock = "-", set(), [], [f"no result: {exc!r}"], ""
        flags += [f"(c) exit {rc}"] * (rc not in (0, 2, 3))
        if stderr.strip():
            flags.append(f"(c) stderr: {stderr.strip().splitlines()[-1][:100]}")
        per = "; ".join(f"{a}{'*' * (a in named)} {cm:.1f}/{deg:.1f} ({z:.1f}σ)" for a, cm, deg, z in rows)
        print(f"| {name} | {preset}:{seed} | `{opts}` | {rc} | {status} | {','.join(sorted(named)) or '-'} "
              f"| {per} | {clock or '-'} | {'; '.join(flags) or '-'} |", flush=True)


if __name__ == "__main__":
    main()
