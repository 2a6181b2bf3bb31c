"""The calib modules a module depends on, read from its import statements (no import is executed).

Used for cache keys (a stage's code digest covers every module it can run) and for the test that
imports run one way (cli → pipeline → {frontend, estimator} → core).
"""
from __future__ import annotations

import ast
import functools
import importlib.util
import os
from pathlib import Path

ROOT_PACKAGE = "calib"


@functools.lru_cache(maxsize=None)
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
    return _parsed(path, _stamp(path))[1]


def imported_modules(name, path):
    """The calib modules named by the import statements of ``name`` (source at ``path``), anywhere in
    the file (function-level imports included). ``from pkg import sub`` counts ``pkg.sub`` when that
    is a module, the submodule behind ``sub`` when ``pkg`` loads it lazily, else ``pkg``."""
    package = name if Path(path).name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for module, level, names in _parsed(str(path), _stamp(path))[0]:
        if module is None:  # import a, b.c
            found.update(names)
            continue
        base = module
        if level:
            parts = package.split(".")
            base = ".".join(parts[:len(parts) - level + 1] + ([module] if module else []))
        lazy = lazy_exports_of(base)
        for a in names:
            sub = f"{base}.{lazy.get(a, a)}"
            found.add(sub if _source(sub) else base)
    return {m for m in found if _source(m)}


def _stamp(path):
    st = os.stat(path)
    return st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=None)
def _parsed(path, stamp):
    """A source file's import statements, ((module or None for ``import``, level, names), ...), and its
    literal ``EXPORTS`` dict ({} if none); cached per (path, mtime, size), so the stages of one
    ``calib run`` read each file once."""
    tree = ast.parse(Path(path).read_text(), filename=path)
    imports = []
    for node in _statements(tree.body):
        if isinstance(node, ast.Import):
            imports.append((None, 0, tuple(a.name for a in node.names)))
        elif isinstance(node, ast.ImportFrom):
            imports.append((node.module or "", node.level, tuple(a.name for a in node.names)))
    exports = next((ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
                    and any(getattr(t, "id", None) == "EXPORTS" for t in node.targets)), {})
    return tuple(imports), exports


def _statements(body):
    """Every statement in ``body``, nested blocks included (function and class bodies, branches,
    handlers, match cases), but not expressions, which cannot hold an import: ~5× fewer nodes than
    ``ast.walk``."""
    for node in body:
        yield node
        for _, value in ast.iter_fields(node):
            if isinstance(value, list) and value and isinstance(value[0], (ast.stmt, ast.excepthandler,
                                                                          ast.match_case)):
                yield from _statements(value)


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
