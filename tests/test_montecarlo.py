"""`calib montecarlo`: the study driver writes its tables and figure, resumes instead of recomputing,
is reproducible from its seeds (locally and on a Dask cluster), and rejects bad input cleanly."""

import multiprocessing
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from calib.pipeline import montecarlo as mc
from calib.cli.main import app
from calib.pipeline.formats.io import InputError

CELL = [(1e-4, 10.0)]
TINY = dict(cells=CELL, trajectories=[1, 3], methods=("hybrid", "wang"), progress=None)


def without_time(path):
    """runs.csv text without the wall-clock column (the only one that is not a function of the seeds)."""
    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    return df.drop(columns="time_s").to_csv(index=False)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("mc") / "study"
    return out, mc.run_study(out, runs=2, jobs=1, **TINY)


def test_study_writes_runs_summary_and_figure(study):
    out, res = study
    runs = pd.read_csv(out / "runs.csv")
    # one final row per run, plus the intermediate stages (hybrid: init and IVE; wang: init)
    assert set(runs.groupby("method")["stage"].agg(lambda s: tuple(sorted(set(s)))).items()) == {
        ("hybrid", ("final", "init", "ive")), ("wang", ("final", "init"))}
    runs = runs[runs["stage"] == "final"]
    assert len(runs) == 1 * 2 * 2 * 2 and res["computed"] == 8 and res["skipped"] == 0
    assert list(runs.columns[:6]) == ["sigma_tdoa", "sigma_doa_deg", "trajectory", "run", "method", "stage"]
    assert runs["ok"].all() and runs["converged"].notna().all()
    assert set(runs["method"]) == {"hybrid", "wang"} and set(runs["trajectory"]) == {1, 3}
    # plausible errors for 0.1 ms / 10°: centimetres to decimetres, a few degrees, sub-ms offsets
    assert runs["position_rmse_m"].between(0.005, 0.5).all()
    assert runs["orientation_paper_deg"].between(0.1, 15).all()
    assert (runs["offset_rmse_s"] < 1e-3).all() and runs["crlb_position_rmse_m"].notna().all()
    # same scene for both methods of a run (the seed does not depend on the method)
    assert (runs.groupby(["trajectory", "run"])["seed"].nunique() == 1).all()
    summary = pd.read_csv(out / "summary.csv")
    assert len(summary) == 5 and set(summary["stage"]) == {"init", "ive", "final"}  # hybrid 3 stages, wang 2
    summary = summary[summary["stage"] == "final"]
    assert len(summary) == 2 and set(summary["method"]) == {"hybrid", "wang"}
    for _, r in summary.iterrows():
        sel = runs[runs["method"] == r["method"]]
        assert r["runs"] == 4 and r["failed"] == 0
        assert r["loc_cm"] == pytest.approx(100 * mc.iqr_mean(sel["position_rmse_m"]), rel=1e-5)
        assert r["drift_ppm"] == pytest.approx(1e6 * mc.iqr_mean(sel["relative_drift_rmse"]), rel=1e-5)
        assert r["converged_pct"] == pytest.approx(100 * sel["converged"].mean())
    hyb = summary.set_index("method").loc["hybrid"]
    assert (hyb["paper_loc_cm"], hyb["paper_ang_deg"]) == mc.PAPER_FINAL[(1e-4, 10.0)]
    png = (out / "fig3.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert not (out / "parts").exists()


def test_iqr_mean_is_the_mean_between_the_quartiles():
    x = np.array([1.0, 2.0, 3.0, 4.0, 100.0])     # quartiles 2 and 4 → mean of 2, 3, 4
    assert mc.iqr_mean(x) == pytest.approx(3.0)
    assert mc.iqr_mean([np.nan, 5.0]) == 5.0 and np.isnan(mc.iqr_mean([]))
    assert mc.iqr_mean([1.0, 3.0]) == 2.0  # no value strictly between the quartiles: the median


@pytest.mark.slow
def test_resume_computes_only_missing_runs_and_matches_a_fresh_study(study, tmp_path):
    fresh, _ = study
    out = tmp_path / "grown"
    first = mc.run_study(out, runs=1, jobs=1, **TINY)
    assert first["computed"] == 4
    before = pd.read_csv(out / "runs.csv", dtype=str)
    res = mc.run_study(out, runs=2, jobs=2, **TINY)                 # grows the study, on 2 local processes
    assert res["computed"] == 4 and res["skipped"] == 4
    key = mc.KEY + ["stage"]
    after = pd.read_csv(out / "runs.csv", dtype=str).set_index(key)
    # the first runs were not recomputed: even their wall-clock times are unchanged
    pd.testing.assert_frame_equal(after.loc[before.set_index(key).index], before.set_index(key))
    assert without_time(out / "runs.csv") == without_time(fresh / "runs.csv")
    again = mc.run_study(out, runs=2, jobs=1, **TINY)
    assert again["computed"] == 0 and again["skipped"] == 8


def test_interrupted_study_keeps_finished_chunks_and_resumes(study, tmp_path, monkeypatch):
    fresh, _ = study
    out = tmp_path / "killed"
    real = mc._run_chunk
    calls = []

    def dying(tasks, settings):
        calls.append(len(tasks))
        if len(calls) == 3:
            raise KeyboardInterrupt  # as if the user pressed Ctrl-C while the third chunk ran
        return real(tasks, settings)

    monkeypatch.setattr(mc, "_run_chunk", dying)
    with pytest.raises(KeyboardInterrupt):
        mc.run_study(out, runs=2, jobs=1, chunk_size=1, **TINY)
    parts = sorted((out / "parts").glob("part-*.csv"))
    assert parts and not (out / "runs.csv").exists()                  # written as the interrupt went up
    finals = sum((pd.read_csv(p)["stage"] == "final").sum() for p in parts)
    assert finals == 4                                                # 2 runs × 2 methods, complete rows
    monkeypatch.setattr(mc, "_run_chunk", real)
    res = mc.run_study(out, runs=2, jobs=1, **TINY)
    assert res["computed"] == 4 and res["skipped"] == 4
    assert without_time(out / "runs.csv") == without_time(fresh / "runs.csv")


@pytest.mark.skipif(not mc._can_fork(), reason="local workers are forked on Linux only")
def test_an_interrupt_in_a_worker_stops_every_worker(tmp_path, monkeypatch):
    from calib.pipeline import studyrun

    real = studyrun.run_chunk

    def dying(tasks, settings):
        if tasks[0][3] == 1:
            raise KeyboardInterrupt   # as if the worker were interrupted in its run 1
        time.sleep(30)                # the other worker would compute on
        return real(tasks, settings)

    monkeypatch.setattr(studyrun, "run_chunk", dying)   # the forked workers inherit it
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        mc.run_study(tmp_path / "s", runs=2, jobs=2, chunk_size=1, figure=False, **TINY)
    assert time.perf_counter() - t0 < 20          # did not wait for the sleeping worker
    deadline = time.monotonic() + 5
    while multiprocessing.active_children() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert multiprocessing.active_children() == []


def test_workers_are_not_forked_beside_another_thread():
    if not sys.platform.startswith("linux"):
        assert not mc._can_fork()
        return
    assert mc._can_fork()                 # the test process: one thread
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert not mc._can_fork()         # e.g. a notebook kernel's threads: joblib's fresh processes instead
    finally:
        stop.set()
        t.join()


def _alive(pid):
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not mc._can_fork(), reason="local workers are forked on Linux only")
def test_a_forked_worker_ends_when_the_study_process_is_killed():
    script = ("import multiprocessing as mp, os, time\n"
              "from calib.pipeline import montecarlo as mc\n"
              "parent = os.getpid()\n"
              "def worker():\n"
              "    null = os.open(os.devnull, os.O_WRONLY); os.dup2(null, 1); os.dup2(null, 2)  # not our pipes\n"
              "    mc._worker_init(parent); time.sleep(60)\n"
              "p = mp.get_context('fork').Process(target=worker)\n"
              "p.start(); print(p.pid, flush=True); os._exit(0)\n")   # the study's process vanishes
    pid = int(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                             timeout=60).stdout)
    deadline = time.monotonic() + 5 * mc.PARENT_POLL_S + 2
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(pid)


@pytest.mark.slow
def test_dask_cluster_gives_the_same_rows(study, tmp_path):
    distributed = pytest.importorskip("distributed")
    fresh, _ = study
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as c:
        res = mc.run_study(tmp_path / "dask", runs=2, scheduler=c.scheduler_address, **TINY)
    assert res["computed"] == 8
    assert without_time(tmp_path / "dask" / "runs.csv") == without_time(fresh / "runs.csv")


def test_resume_with_other_settings_is_refused(study):
    out, _ = study
    with pytest.raises(InputError, match="study.json.*sigma_odo"):
        mc.run_study(out, runs=2, jobs=1, sigma_odo=0.01, **TINY)


def test_grid_file(tmp_path):
    p = tmp_path / "grid.toml"
    p.write_text("sigma_tdoa = [5e-5, 5e-4]\nsigma_doa_deg = [15]\ntrajectories = [2]\nruns = 3\n"
                 "methods = ['wang']\n")
    g = mc.read_grid(p)
    assert g["cells"] == [(5e-5, 15.0), (5e-4, 15.0)] and g["trajectories"] == [2] and g["runs"] == 3
    assert g["methods"] == ["wang"] and g["sigma_odo"] == mc.SIGMA_ODO
    for text, msg in (("runs = 0", "runs"), ("methods = ['magic']", "methods"), ("trajectories = [4]", "traject"),
                      ("colour = 3", "unknown key 'colour'"), ("runs = [", "invalid TOML"),
                      ("cells = [[1e-4, 5]]\nsigma_tdoa = [1e-4]", "either")):
        p.write_text(text)
        with pytest.raises(InputError, match=msg) as e:
            mc.read_grid(p)
        assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_cli_runs_a_grid_and_rejects_bad_input_without_output(tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli"
    r = runner.invoke(app, ["montecarlo", "-o", str(out), "--runs", "1", "--sigma-tdoa", "0.1", "--sigma-doa", "10",
                            "--trajectories", "2", "--methods", "wang", "--jobs", "1", "--no-crlb",
                            "--no-check-convergence", "-q"])
    assert r.exit_code == 0, r.output
    runs = pd.read_csv(out / "runs.csv")
    runs = runs[runs["stage"] == "final"].reset_index(drop=True)
    assert len(runs) == 1 and runs.loc[0, "method"] == "wang" and runs["converged"].isna().all()
    assert runs.loc[0, "sigma_tdoa"] == pytest.approx(1e-4)
    bad = tmp_path / "bad"
    for args, msg in ((["--methods", "magic"], "methods"), (["--sigma-doa", "x"], "--sigma-doa"),
                      (["--grid", str(tmp_path / "nope.toml")], "nope.toml: file not found"),
                      (["--jobs", "0"], "jobs")):
        r = runner.invoke(app, ["montecarlo", "-o", str(bad), "-q", *args])
        assert r.exit_code == 2 and msg in r.output and r.output.startswith("error: "), r.output
        assert not bad.exists()


def test_chunks_shrink_cover_every_task_in_order_and_honour_a_fixed_size():
    tasks = list(range(1000))
    for workers in (1, 2, 16):
        chunks = mc._chunks(tasks, workers)
        assert [t for c in chunks for t in c] == tasks                     # contiguous, in order, each once
        sizes = [len(c) for c in chunks]
        assert max(sizes) <= mc.MAX_CHUNK and sizes == sorted(sizes, reverse=True)
        # the last chunks are short: the workers finish together (the tail is about one run per worker)
        assert sizes[-1] == 1 and sum(sizes[-workers:]) <= 2 * workers
    assert [len(c) for c in mc._chunks(tasks[:7], 4, size=3)] == [3, 3, 1]
    assert mc._chunks([], 4) == []


@pytest.mark.slow
def test_rows_are_the_same_whatever_the_workers_and_the_chunk_sizes(study, tmp_path):
    import os

    fresh, _ = study                                    # in this process, the default (guided) chunks
    # (2 processes with the default chunks: test_resume_computes_only_missing_runs_and_matches_a_fresh_study)
    for jobs, size, n_chunks in ((1, 3, 2), (2, 1, 4)):
        out = tmp_path / f"jobs{jobs}-size{size}"
        res = mc.run_study(out, runs=2, jobs=jobs, chunk_size=size, figure=False, **TINY)
        assert res["computed"] == 8 and len(res["timing"]["chunks"]) == n_chunks   # 4 tasks (2 methods each)
        workers = {c["worker"].rsplit(":", 1)[1] for c in res["timing"]["chunks"]}
        assert (workers == {str(os.getpid())}) == (jobs == 1)                    # jobs=2: worker processes
        assert without_time(out / "runs.csv") == without_time(fresh / "runs.csv")
