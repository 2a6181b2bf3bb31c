"""Where the paper lab's eight real feature sets are: ``$CALIB_REAL_WORLD``, else ``../shared/real_world`` beside
the checkout (the project's layout). A benchmark that finds none says so and where it looked, rather than
printing nothing (from a git worktree elsewhere, set the variable)."""
from __future__ import annotations

import os
from pathlib import Path

ENV = "CALIB_REAL_WORLD"


def real_world_dir() -> Path:
    return Path(os.environ.get(ENV) or Path(__file__).resolve().parents[2] / "shared" / "real_world")


def not_found(path: Path) -> str:
    return f"real data: no feature sets at {path} (set {ENV} to their folder)"
