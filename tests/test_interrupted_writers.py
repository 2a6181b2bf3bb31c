"""An interrupt at any point of a writer leaves the old output or the new one, whole, and no litter.

Each writer is run once to count the file-system calls it makes, then once per call with SIGINT raised right
after that call returns (``signal.raise_signal`` under the command's own handlers, as a real Ctrl-C or SIGTERM
arriving during the call): wherever it lands, no temporary or lock file is left, and the target is either
what it was or what the writer meant to write, with a manifest that matches it.
"""
from __future__ import annotations

import fcntl
import io
import os
import signal
from pathlib import Path

import pytest

from calib.cli import signals
from calib.pipeline.formats.io import atomic_write_text
from calib.pipeline.formats.outputs import STAGE_STAMP, check_file_replaceable, check_replaceable, publish, write_file

# the calls through which a writer creates, renames, removes or locks something
CALLS = [(os, "open"), (os, "mkdir"), (os, "replace"), (os, "rename"), (os, "chmod"), (os, "unlink"),
         (os, "rmdir"), (os, "ftruncate"), (io, "open"), (fcntl, "flock")]


def _instrument(monkeypatch, interrupt_at):
    """Wrap CALLS; SIGINT right after call number ``interrupt_at`` (1-based; 0: never). Returns the counter."""
    count = [0]
    for module, name in CALLS:
        real = getattr(module, name)

        def wrapped(*args, _real=real, **kwargs):
            result = _real(*args, **kwargs)
            count[0] += 1
            if count[0] == interrupt_at:
                signal.raise_signal(signal.SIGINT)
            return result

        monkeypatch.setattr(module, name, wrapped)
    return count


def _litter(folder):
    return sorted(p.name for p in Path(folder).rglob(".*")
                  if ".calib-tmp-" in p.name or ".calib-old-" in p.name or p.name.endswith(".calib-lock"))


def _write_file(root):
    write_file(root / "out.txt", "new\n", command="calib test")


def _publish(root):
    with publish([root / "a", root / "b"], command="calib test") as (a, b):
        (a / "x.txt").write_text("new a\n")
        (b / "y.txt").write_text("new b\n")


def _stamp(root):
    atomic_write_text(root / "a" / STAGE_STAMP, "new stamp\n")


def _before(root):
    """An earlier calib output in ``root``: a single file and two published folders."""
    write_file(root / "out.txt", "old\n", command="calib test")
    with publish([root / "a", root / "b"], command="calib test") as (a, b):
        (a / "x.txt").write_text("old a\n")
        (b / "y.txt").write_text("old b\n")
    atomic_write_text(root / "a" / STAGE_STAMP, "old stamp\n")


def _state(root):
    """What a user would find: every file's text (calib's bookkeeping aside), after checking the manifests."""
    check_file_replaceable(root / "out.txt")  # listed, unedited, in its folder's manifest (or absent)
    for sub in ("a", "b"):
        check_replaceable(root / sub)
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted(root.rglob("*"))
            if p.is_file() and (not p.name.startswith(".") or p.name == STAGE_STAMP)}


def _run(root, writer, monkeypatch, interrupt_at):
    previous = signals.install()
    try:
        with monkeypatch.context() as m:
            count = _instrument(m, interrupt_at)
            try:
                writer(root)
                interrupted = False
            except KeyboardInterrupt:
                interrupted = True
        return count[0], interrupted
    finally:
        signals.restore(previous)
        signals._pending = None


@pytest.mark.parametrize("writer", [_write_file, _publish, _stamp], ids=["write_file", "publish", "stamp"])
@pytest.mark.parametrize("fresh", [True, False], ids=["new", "replacing"])
def test_an_interrupt_anywhere_leaves_old_or_new_and_no_litter(tmp_path, monkeypatch, writer, fresh):
    def prepared(name):
        root = tmp_path / name
        root.mkdir()
        if not fresh:
            _before(root)
        elif writer is _stamp:
            (root / "a").mkdir()
        return root

    reference = prepared("reference")
    old = _state(reference) if not fresh else None
    n, interrupted = _run(reference, writer, monkeypatch, 0)
    new = _state(reference)
    assert n > 3 and not interrupted and not _litter(reference)
    for k in range(1, n + 1):
        root = prepared(f"k{k}")
        before = _state(root) if not fresh else {}
        _, interrupted = _run(root, writer, monkeypatch, k)
        assert interrupted, k
        assert not _litter(root), (k, _litter(root))
        after = _state(root)
        assert after in (before, new), (k, after)
        if not fresh:
            assert before == old
