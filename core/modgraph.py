"""The calib modules a module depends on, read from its import statements (no import is executed).

Used for cache keys (a stage's code digest covers every module it can run) and for the test that
imports run one way (cli → pipeline → {frontend, estimator} → core).
"""
from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

ROOT_PACKAGE = "calib"


def _source(name):
    """Path of module/package ``name``'s source file, or None when it is not a calib module."""
    if name != ROOT_PACKAGE and not name.startswith(ROOT_PACKAGE + "."):
        return None
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    return spec.origin if spec is not None and spec.origin and spec.origin.endswith(".py") else None


def lazy_exports_of(package):
    """{name: submodule} of a package that loads its names lazily (``EXPORTS`` in its ``__init__``,
    see ``calib.lazy``), else {}."""
    path = _source(package)
    if path is None or not path.endswith("__init__.py"):
        return {}
    for node in ast.parse(Path(path).read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "EXPORTS" for t in node.targets):
            return ast.literal_eval(node.value)
    return {}


def imported_modules(name, path):
    """The calib modules named by the import statements of ``name`` (source at ``path``), anywhere in
    the file (function-level imports included). ``from pkg import sub`` counts ``pkg.sub`` when that
    is a module, the submodule behind ``sub`` when ``pkg`` loads it lazily, else ``pkg``."""
    tree = ast.parse(Path(path).read_text(), filename=str(path))
    package = name if Path(path).name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            lazy = lazy_exports_of(base)
            for a in node.names:
                sub = f"{base}.{a.name}"
                if a.name in lazy:
                    sub = f"{base}.{lazy[a.name]}"
                found.add(sub if _source(sub) else base)
    return {m for m in found if _source(m)}


def module_closure(modules):
    """{module name: source path} for ``modules`` and every calib module they import, transitively
    (each package's ``__init__`` included, since importing a submodule runs it)."""
    seen, todo = {}, list(modules)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _source(name)
        if path is None:
            continue
        seen[name] = path
        parts = name.split(".")
        todo.extend(".".join(parts[:k]) for k in range(1, len(parts)))
        todo.extend(imported_modules(name, path))
    return seen
