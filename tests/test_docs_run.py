"""Every command and code block of README.md and docs/*.md runs, as written, in a fresh folder, chained as a reader
would run them, and the numbers the text states about its output are checked (docs/results.md's tables and
docs/cli.md's `--help` blocks excepted: tests/test_docs.py checks cli.md against the CLI).

A fenced block is one of:
- ``` / ```bash / ```sh: shell lines; each `calib ...` runs as `python -m calib ...` and must exit 0;
- ```python: run with this Python in the page's folder;
- ```toml: a file the page's commands use, named by `<!-- file: NAME -->` on the line before the fence (written
  into the folder before the page's commands run), else marked not run; always parsed;
- ```text: a layout or an output, not code;
- any block with `<!-- not run: REASON -->` on the line before its fence (a user's own hardware, the full
  4-minute study): its `calib` commands are still parsed by tests/test_docs.py.
A page listed in PAGE_TESTS has every runnable block run, in order, by its test; any other page may hold no
unmarked runnable block (test_every_block_is_run_or_marked)."""
import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from calib.tomlcompat import tomllib

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```(\w*)\n(.*?)\n```$", re.S | re.M)
MARKER = re.compile(r"<!--\s*(not run|file):\s*(.*?)\s*-->\s*$")
SHELL, PYTHON, TOML, TEXT = ("", "bash", "sh"), "python", "toml", "text"
# pages whose every runnable block runs in a test of this module (or tests/test_docs.py's localisation test)
PAGE_TESTS = {"README.md": "test_readme_runs", "docs/tutorial.md": "test_tutorial_runs",
              "docs/frontend.md": "test_frontend_page_runs", "docs/simulation.md": "test_simulation_page_runs",
              "docs/localisation.md": "test_localisation_example_finds_the_held_back_source"}
NOT_CHECKED_HERE = {"docs/results.md", "docs/cli.md"}  # measured tables; generated --help (tests/test_docs.py)
# the two non-calib commands the docs show, and why running them here would be wrong
NOT_RE_RUN = {("pip", "install"): "the install step: the test runs in the installed package",
              ("python", "-m"): "the test suite itself (python -m pytest): this is it"}


@dataclass(frozen=True)
class Block:
    page: str
    line: int  # of the opening fence, from 1
    lang: str
    body: str
    marker: tuple = None  # ("not run", reason) or ("file", name)

    @property
    def runnable(self):
        return self.marker is None and self.lang in SHELL + (PYTHON,)


def doc_pages():
    return [p for p in ["README.md", *(f"docs/{q.name}" for q in sorted((ROOT / "docs").glob("*.md")))]
            if p not in NOT_CHECKED_HERE]


def page_blocks(page):
    text = (ROOT / page).read_text()
    out = []
    for m in FENCE.finditer(text):
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        mark = MARKER.search(before)
        out.append(Block(page, text.count("\n", 0, m.start()) + 1, m.group(1), m.group(2),
                         (mark.group(1), mark.group(2)) if mark else None))
    return out


def shell_commands(body):
    """The commands of a shell block: one list of words per command (`;` and `&&` separate, `#` comments)."""
    for line in body.splitlines():
        lex = shlex.shlex(line, posix=True, punctuation_chars=";&")
        lex.whitespace_split = True
        cmd = []
        for word in list(lex) + [";"]:
            if word in (";", "&&"):
                if cmd:
                    yield cmd
                cmd = []
            else:
                cmd.append(word)


def run_page(page, folder, blocks=None):
    """Run the page's blocks (all by default) in `folder` as a reader would; return [(block, [stdout, ...])]."""
    env = {**os.environ, "COLUMNS": "120"}
    blocks = page_blocks(page) if blocks is None else blocks
    for b in blocks:
        if b.marker and b.marker[0] == "file":
            (folder / b.marker[1]).write_text(b.body + "\n")
    results = []
    for b in (b for b in blocks if b.runnable):
        outs = []
        if b.lang == PYTHON:
            outs.append(_run([sys.executable, "-c", b.body], folder, env, b))
        for cmd in shell_commands(b.body) if b.lang in SHELL else ():
            if tuple(cmd[:2]) in NOT_RE_RUN:
                continue
            assert cmd[0] == "calib", f"{page}:{b.line}: {cmd[0]!r} is no command this test knows: {cmd}"
            outs.append(_run([sys.executable, "-m", "calib", *cmd[1:]], folder, env, b))
        results.append((b, outs))
    return results


def _run(argv, folder, env, block):
    proc = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, f"{block.page}:{block.line}: {shlex.join(argv[1:])[:200]} exit " \
                                 f"{proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    return proc.stdout


def test_every_block_is_run_or_marked():
    """A new block in README.md or docs/*.md is run by its page's test or says why not: none goes unchecked."""
    seen = 0
    for page in doc_pages():
        for b in page_blocks(page):
            seen += 1
            where = f"{page}:{b.line}"
            assert b.lang in SHELL + (PYTHON, TOML, TEXT), f"{where}: unknown block language {b.lang!r}"
            if b.marker:
                assert b.marker[1], f"{where}: a marker gives its reason or file name"
                assert b.marker[0] == "not run" or b.lang == TOML, f"{where}: only TOML blocks are files"
            if b.lang == TOML:
                tomllib.loads(b.body)  # every TOML example parses
                assert b.marker, f"{where}: a TOML block is a file (<!-- file: NAME -->) or marked not run"
            if b.runnable:
                assert page in PAGE_TESTS, f"{where}: no test runs this page's blocks; run it or mark it " \
                                           f"<!-- not run: REASON -->"
            if b.lang in SHELL and b.marker is None:
                for cmd in shell_commands(b.body):
                    assert cmd[0] == "calib" or tuple(cmd[:2]) in NOT_RE_RUN, f"{where}: {cmd}"
    assert seen > 20


def test_shell_commands_split_as_a_shell_would():
    got = list(shell_commands("pip install -e '.[x]' && calib run a -o b  # c; d\ncalib chirp -o k/; calib init m"))
    assert got == [["pip", "install", "-e", ".[x]"], ["calib", "run", "a", "-o", "b"], ["calib", "chirp", "-o", "k/"],
                   ["calib", "init", "m"]]


def _link_sample_data(folder):
    (folder / "sample_data").symlink_to(ROOT / "sample_data")  # the pages' commands run from the repository root


def _stated(page, pattern):
    m = re.search(pattern, (ROOT / page).read_text())
    assert m, f"{page} no longer states {pattern!r}"
    return m


@pytest.mark.slow
def test_readme_runs(tmp_path):
    """README.md: the set-up line, the tour (simulate → run twice → each stage alone → export → a fiftieth of
    the study → chirp) and the notebook block, in one folder; the numbers the README states about them."""
    _link_sample_data(tmp_path)
    res = run_page("README.md", tmp_path)
    setup, tour, notebook = (outs for _, outs in res)
    assert (tmp_path / "calib-out/calibration/calibration.json").exists()
    # the bundled sample is a clean simulated session: no false alarm in the main job (the leave-one-array-out
    # check once named A2 for a 1 mm move of A3, 0.5 σ)
    verdict = json.loads((tmp_path / "calib-out/calibration/report.json").read_text())["verdict"]
    assert verdict["status"] == "ok" and verdict["flagged_arrays"] == [], verdict
    # "again: every stage is skipped (content hashes)"
    first, again = tour[1], tour[2]
    assert "skipped" not in first
    assert "skipped (unchanged): features, estimate, report" in again, again[-500:]
    # ("in well under a second of estimation" is a speed figure: benchmarks/bench_run.py's estimate_s, not a test)
    # the stages alone give the calibration `calib run` gave (same features, deterministic estimator)
    import pandas as pd

    a = pd.read_csv(tmp_path / "out/calibration/arrays.csv")
    b = pd.read_csv(tmp_path / "cal/arrays.csv")
    assert np.allclose(a[["x", "y", "z"]], b[["x", "y", "z"]], atol=1e-6)
    metrics = json.loads((tmp_path / "out/report/metrics.json").read_text())
    assert metrics["position_rmse_m"] < 0.02  # this session calibrates to ~0.2 cm; a regression breaks 2 cm
    assert np.load(tmp_path / "mics.npy").shape == (3, 5 * 6)  # 5 arrays of 6 mics, reference frame
    # "a fiftieth of the study": 4 runs of each of the 9 cells x 3 trajectories, both methods
    runs = pd.read_csv(tmp_path / "study/runs.csv")
    final = runs[runs["stage"] == "final"]
    assert final.groupby("method").size().to_dict() == {"hybrid": 4 * 9 * 3, "wang": 4 * 9 * 3}
    ours = final[final["method"] == "hybrid"]
    assert ours["converged"].mean() >= 0.99  # "converges in 100 % of runs"
    ratio = (ours["position_rmse_m"] / ours["crlb_position_rmse_m"]).median()
    assert 0.7 < ratio < 1.3, ratio  # "sits at the Cramér–Rao bound" (0.9 measured; a biased solver breaks it)
    assert {"chirp.wav", "schedule.csv", "chirp.toml"} <= {p.name for p in (tmp_path / "kit").iterdir()}
    assert "A2" in notebook[0]
    # "localises a sound ... in 39 lines": the localisation page's block has that many
    n = int(_stated("README.md", r"calibrated\s+clocks, in (\d+) lines").group(1))
    (loc,) = [b for b in page_blocks("docs/localisation.md") if b.lang == PYTHON]
    assert n == len(loc.body.splitlines())


@pytest.mark.slow
def test_tutorial_runs(tmp_path):
    """docs/tutorial.md, sections 0-8 in order in one folder (the former tests/test_docs.py tutorial test)."""
    res = run_page("docs/tutorial.md", tmp_path)
    assert np.load(tmp_path / "out/mics.npy").shape == (3, 5 * 6)  # "(3, all mics)"
    evaluate_json = next(o for b, outs in res for o in outs if o.lstrip().startswith("{"))
    assert json.loads(evaluate_json)["position_rmse_m"] < 0.02
    for out in ("out-mine", "out-permic", "out-bag"):  # "Each calibrates as out-mine did"
        metrics = json.loads((tmp_path / out / "report/metrics.json").read_text())
        assert metrics["position_rmse_m"] < 0.05, (out, metrics)
    text = (tmp_path / "mine/session.toml").read_text()
    assert "channels = [0, 1, 2, 3, 4, 5]" in text  # as the page says calib init writes
    robot = tomllib.loads((tmp_path / "bagrec/session.toml").read_text())["robot"]
    stated = float(_stated("docs/tutorial.md", r"the speaker (\d+) cm off the base").group(1))
    assert abs(100 * np.hypot(*robot["speaker_offset"][:2]) - stated) < 0.5  # the lever arm that turns with yaw


@pytest.mark.slow
def test_frontend_page_runs(tmp_path):
    _link_sample_data(tmp_path)
    run_page("docs/frontend.md", tmp_path)
    for d in ("out/diagnostics", "diag"):  # the first line's default diagnostics folder, the second's --diagnostics
        assert {"diagnostics.json", "detections.png"} <= {p.name for p in (tmp_path / d).iterdir()}
    assert (tmp_path / "feats/tdoa_m.csv").exists() and (tmp_path / "out/features/doa.csv").exists()


@pytest.mark.slow
def test_simulation_page_runs(tmp_path):
    """docs/simulation.md: its three `calib simulate` lines (the scenario file is the page's TOML block) and what
    their comments say."""
    import pandas as pd

    run_page("docs/simulation.md", tmp_path)
    def scenario(name):
        return json.loads((tmp_path / "out" / name / "truth/manifest.json").read_text())["scenario"]

    sim = scenario("sim")
    assert (len(sim["arrays"]), len(sim["t_emit"]), sim["rt60"]) == (5, 14, 0.3)  # "5 arrays, 14 chirps, RT60 0.3 s"
    assert len(pd.read_csv(tmp_path / "out/sim/events.csv")) == 14
    lab = scenario("lab")
    assert lab["rt60"] == 0 and lab["snr"] in (None, float("inf"), "inf")  # "anechoic, noise-free"
    x = scenario("x")  # the page's TOML file, the command line's --seed winning over its seed = 4
    toml = tomllib.loads(next(b.body for b in page_blocks("docs/simulation.md") if b.lang == TOML))
    assert (x["preset"], x["seed"], x["rt60"], x["chirp"]["duration"]) == ("lab3", 3, 0.4, 0.25)
    assert [a["name"] for a in x["arrays"]] == [a["name"] for a in toml["arrays"]]
    for got, want in zip(x["arrays"], toml["arrays"]):
        assert np.allclose(got["position"], want["position"]) and np.allclose(got["quat"], [1, 0, 0, 0])
        assert got["drift"] == want.get("drift", 0.0)
    assert x["arrays"][1]["tau"] == 0.35


def test_montecarlo_grid_file_is_the_papers_grid(tmp_path):
    """docs/montecarlo.md's grid file (not run: the full grid) reads, and is what it says: the paper's defaults."""
    from calib.pipeline.montecarlo import paper_grid, read_grid

    (toml,) = [b for b in page_blocks("docs/montecarlo.md") if b.lang == TOML]
    (tmp_path / "grid.toml").write_text(toml.body)
    grid, paper = read_grid(tmp_path / "grid.toml"), paper_grid()
    assert len(grid["cells"]) == 9 and sorted(map(tuple, grid["cells"])) == sorted(map(tuple, paper["cells"]))
    for key in ("trajectories", "runs", "methods", "sigma_odo", "base_seed"):
        assert grid[key] == paper[key], key
