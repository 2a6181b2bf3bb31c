"""Package structure: one import package ``calib`` whose layers import one way
(cli → pipeline → {frontend, estimator} → core), read from the import statements of every module."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from .modgraph import imported_modules

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"core": "calib", "frontend": "calib.frontend", "estimator": "calib.estimator",
          "pipeline": "calib.pipeline", "cli": "calib.cli"}
# what each layer may import besides itself and the core (the root package's own modules)
ALLOWED = {"core": set(), "frontend": set(), "estimator": set(),
           "pipeline": {"frontend", "estimator"}, "cli": {"pipeline", "frontend", "estimator"}}
ENTRY_POINTS = {"calib.__main__"}  # ``python -m calib`` runs the CLI by definition


def layer_of(module):
    for layer, pkg in sorted(LAYERS.items(), key=lambda kv: -len(kv[1])):
        if module == pkg or module.startswith(pkg + "."):
            return layer
    raise AssertionError(module)


def sources(folder):
    """The Python files of a top-level folder, subpackages included."""
    return sorted(f for f in (ROOT / folder).rglob("*.py") if "__pycache__" not in f.parts)


def all_modules():
    for layer, pkg in LAYERS.items():
        for f in sources(layer):
            parts = f.relative_to(ROOT / layer).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            yield ".".join((pkg, *parts)), f


@pytest.mark.parametrize("name,path", list(all_modules()), ids=lambda v: str(v))
def test_imports_run_one_way(name, path):
    if name in ENTRY_POINTS:
        return
    layer = layer_of(name)
    for dep in imported_modules(name, path):
        dep_layer = layer_of(dep)
        assert dep_layer in ALLOWED[layer] | {layer, "core"}, f"{name} ({layer}) imports {dep} ({dep_layer})"


def test_no_bare_top_level_imports():
    """Every project import goes through ``calib.``: no module imports ``pipeline`` etc. as top level."""
    bad = []
    for folder in ("core", "frontend", "estimator", "pipeline", "cli", "tests", "benchmarks"):
        for f in sources(folder):
            for node in ast.walk(ast.parse(f.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
                bad += [f"{f.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in LAYERS]
    assert not bad, bad


MAX_FUNCTION_LINES = 80  # the project's style rule (developer guide): split longer functions


def test_no_function_over_80_lines():
    long = []
    for layer in LAYERS:
        for f in sources(layer):
            for node in ast.walk(ast.parse(f.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    if n > MAX_FUNCTION_LINES:
                        long.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


# pipeline/ by concern: what each part may import from the rest of pipeline (besides itself); the
# orchestration modules at the top (run, features, sessiontools, montecarlo) may use every part.
PIPELINE_PARTS = {"formats": set(), "simulate": {"formats"}, "report": {"formats", "simulate"}}


@pytest.mark.parametrize("name,path", [m for m in all_modules() if m[0].split(".")[2:3] and
                                       m[0].split(".")[2] in PIPELINE_PARTS], ids=lambda v: str(v))
def test_pipeline_parts_import_one_way(name, path):
    part = name.split(".")[2]
    for dep in imported_modules(name, path):
        bits = dep.split(".")
        if bits[:2] == ["calib", "pipeline"] and len(bits) > 2:
            assert bits[2] in PIPELINE_PARTS[part] | {part}, f"{name} ({part}) imports {dep}"


def _loaded_after(modules, heavy):
    """Which of the modules ``heavy`` a fresh interpreter has loaded after importing ``modules``."""
    import subprocess
    import sys

    code = f"import sys, {', '.join(modules)}; print(','.join(m for m in {tuple(heavy)!r} if m in sys.modules))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_cli_startup_does_not_load_the_heavy_libraries():
    """`calib --help` must not wait for the simulator's or the frontend's libraries (they load on use)."""
    out = _loaded_after(["calib.cli.main"], ["pyroomacoustics", "matplotlib", "scipy.signal", "scipy.spatial",
                                             "calib.frontend.extract", "calib.pipeline.simulate.roomsim"])
    assert out == "", f"loaded at startup: {out}"


def test_feature_extraction_does_not_load_what_it_does_not_use():
    """`calib features` pays for its imports on every run: not scipy.signal and the scipy.stats it pulls
    (~0.4 s), not the estimator."""
    out = _loaded_after(["calib.cli.main", "calib.cli.features", "calib.pipeline.features", "calib.frontend.extract"],
                        ["scipy.signal", "scipy.stats", "calib.estimator"])
    assert out == "", f"loaded for feature extraction: {out}"


def test_feature_extraction_runs_without_scipy_signal():
    """Nor does a features run load scipy.signal / scipy.stats (~0.35 s of CPU, a fifth of the frontend's cost on
    a short session): peak picking and the drift bias's resampling are the frontend's own (frontend.detect,
    frontend.signals)."""
    import subprocess
    import sys
    from pathlib import Path

    lab3 = Path(__file__).resolve().parents[1] / "sample_data" / "lab3"
    code = ("import sys; from calib.pipeline.features import session_features; "
            f"session_features({str(lab3)!r}); "
            "print(','.join(m for m in ('scipy.signal', 'scipy.stats') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out.splitlines()[-1:] in ([], [""]), f"loaded by a features run: {out}"


@pytest.mark.parametrize("package", ["calib.frontend", "calib.estimator"])
def test_exported_names_are_the_objects_not_submodules(package):
    """A package's public names stay functions/classes even after every submodule has been imported (a
    lazily exported name that equals a submodule's name would otherwise become the module)."""
    import importlib
    import pkgutil
    import types

    pkg = importlib.import_module(package)
    for info in pkgutil.iter_modules(pkg.__path__):
        importlib.import_module(f"{package}.{info.name}")
    for name in pkg.__all__:
        assert not isinstance(getattr(pkg, name), types.ModuleType), f"{package}.{name} is a module"
