"""A study's timeline (pipeline.studytiming) and its projection to N workers: the list scheduling against
hand-derived makespans, the projection's parts against a hand-built timeline, and a real study's timeline
(every task once, in its worker, the measured run replayed to its own wall time)."""
import json

import pytest
from typer.testing import CliRunner

from calib.cli.main import app
from calib.pipeline import montecarlo as mc
from calib.pipeline import studytiming as st

TINY = dict(cells=[(1e-4, 10.0)], trajectories=[1, 3], methods=("hybrid", "wang"), progress=None)


def test_list_schedule_hands_each_chunk_to_the_first_free_worker():
    # 2 workers: 3 | 3, then 2 → first free (t=3) ... by hand: w1 3+2+2 = 7, w2 3+2 = 5
    assert st.list_schedule([3, 3, 2, 2, 2], 2) == 7
    assert st.list_schedule([3, 3, 2, 2, 2], 2, ready=1.5) == 8.5      # both start late
    assert st.list_schedule([3, 3, 2, 2, 2], 1) == 12                  # one worker: the sum
    assert st.list_schedule([3, 3, 2, 2, 2], 8) == 3                   # more workers than chunks: the longest
    assert st.list_schedule([1, 1, 1, 1, 9], 4) == 10                  # in order: the long last chunk waits


def _timeline(durations, *, start=100.0, before=0.5, after=2.0, startup=1.0, gap=0.1, mode="local"):
    """A hand-built timeline: one worker runs every task (one chunk per task) after ``startup``."""
    tasks = [(1e-4, 10.0, 1, r, ["hybrid"]) for r in range(len(durations))]
    dispatch = start + before
    t, chunks = dispatch + startup, []
    for task, d in zip(tasks, durations):
        chunks.append({"worker": "h:1", "cpu_before": 0.7, "import_cpu_s": 0.4, "keys": [list(st.task_key(task))],
                       "tasks": [[t, t + d, d * 0.5, d * 0.5]], "received": t + d, "handled_s": 0.01})
        t += d + gap
    collected = t - gap
    return {"start": start, "process_cpu_s": 0.6, "mode": mode, "n_workers": 1,
            "tasks_order": [list(st.task_key(x)) for x in tasks], "chunks": chunks,
            "phases": {"dispatch": {"t": dispatch, "parent_cpu_s": 0.2},
                       "collected": {"t": collected, "parent_cpu_s": 0.3},
                       "end": {"t": collected + after, "parent_cpu_s": 1.8}}}


def test_projection_adds_the_serial_part_the_start_up_and_the_scheduled_chunks():
    durations = [1.0, 2.0, 3.0, 4.0]
    tl = _timeline(durations)
    s = st.summary(tl)
    assert s["before_s"] == pytest.approx(0.5) and s["after_s"] == pytest.approx(2.0)
    assert s["startup_s"] == pytest.approx(1.0) and s["chunk_overhead_s"] == pytest.approx(0.1)
    assert s["task_wall_s"] == pytest.approx(10.0) and s["task_cpu_s"] == pytest.approx(5.0)
    assert s["before_cpu_s"] == pytest.approx(0.2) and s["after_cpu_s"] == pytest.approx(1.5)
    assert s["startup_cpu_s"] == pytest.approx(0.7) and s["cli_start_cpu_s"] == 0.6
    one_each = lambda d, n: [[x] for x in d]  # noqa: E731  (a chunker: one task per chunk)
    # replayed as measured: before + start-up + 4 tasks + 4 chunk overheads + after
    assert st.project(tl, 1, one_each, kind="wall") == pytest.approx(0.5 + 1.0 + 10.0 + 4 * 0.1 + 2.0)
    # on an idle machine: CPU durations, the workers' start-up CPU, the parent's CPU outside the loop
    assert st.project(tl, 1, one_each, kind="cpu") == pytest.approx(0.2 + 1.5 + 0.7 + 5.0 + 4 * 0.1)
    # 2 workers (wall): [1, 2, 3, 4] + 0.1 each → w1 1.1 + 3.1 = 4.2, w2 2.1 + 4.1 = 6.2
    assert st.project(tl, 2, one_each, kind="wall", serial_s=0.0, startup_s=0.0) == pytest.approx(6.2)
    # the study's own chunking, as the study would form it for that many workers
    assert st.project(tl, 2, mc._chunks, kind="wall", serial_s=0.0, startup_s=0.0, overhead_s=0.0) == \
        pytest.approx(st.list_schedule([sum(c) for c in mc._chunks(durations, 2)], 2))


def test_a_studys_timeline_has_every_task_once_and_replays_to_its_wall_time(tmp_path):
    res = mc.run_study(tmp_path / "s", runs=2, jobs=1, chunk_size=1, figure=False, **TINY)
    tl = json.loads(json.dumps(res["timing"]))       # what --timing-log writes
    assert tl["mode"] == "in-process" and tl["n_workers"] == 1
    keys = [tuple(k) for c in tl["chunks"] for k in c["keys"]]
    assert sorted(keys) == sorted(tuple(k) for k in tl["tasks_order"]) and len(keys) == 4   # 2 runs × 2 trajectories
    assert all(len(k) == 5 and k[4] == 2 for k in keys)                                      # both methods per task
    ph = tl["phases"]
    assert tl["start"] <= ph["dispatch"]["t"] <= ph["collected"]["t"] <= ph["end"]["t"]
    for c in tl["chunks"]:
        for start, end, cpu, process_cpu in c["tasks"]:
            assert ph["dispatch"]["t"] <= start < end <= c["received"] <= ph["collected"]["t"]
            assert 0 < cpu <= process_cpu + 1e-3
    s = st.summary(tl)
    assert s["tasks"] == 4 and s["workers_seen"] == 1
    # the measured run list-scheduled on its one worker (after its start-up: importing the estimator) is its
    # own task loop (within 10 %: the part files between chunks vary)
    replay = st.project(tl, 1, lambda d, n: mc._chunks(d, n, size=1), kind="wall", serial_s=0.0)
    assert s["startup_s"] > 0 and replay == pytest.approx(s["loop_s"], rel=0.1)
    # every run's own wall time (time_s of runs.csv) lies within its task's
    final = res["runs"][res["runs"]["stage"] == "final"]
    task_wall = {tuple(k[:4]): end - start for c in tl["chunks"] for k, (start, end, *_) in zip(c["keys"], c["tasks"])}
    for _, r in final.iterrows():
        assert r["time_s"] < task_wall[(r["sigma_tdoa"], r["sigma_doa_deg"], r["trajectory"], r["run"])]


def test_cli_writes_the_timeline_and_never_replaces_a_users_file(tmp_path):
    runner = CliRunner()
    args = ["montecarlo", "-o", str(tmp_path / "study"), "--runs", "1", "--sigma-tdoa", "0.1", "--sigma-doa", "10",
            "--trajectories", "2", "--methods", "wang", "--jobs", "1", "--no-crlb", "--no-check-convergence", "-q"]
    log = tmp_path / "timing.json"
    r = runner.invoke(app, [*args, "--timing-log", str(log)])
    assert r.exit_code == 0, r.output
    tl = json.loads(log.read_text())
    assert len(tl["chunks"]) == 1 and tl["chunks"][0]["keys"] == [[1e-4, 10.0, 2, 0, 1]]
    mine = tmp_path / "mine.json"
    mine.write_text("my notes\n")
    r = runner.invoke(app, [*args[:2], str(tmp_path / "other"), *args[3:], "--timing-log", str(mine)])
    assert r.exit_code == 2 and "mine.json" in r.output and r.output.startswith("error: ")
    assert mine.read_text() == "my notes\n" and not (tmp_path / "other").exists()
