"""The calib modules a module imports, read from its import statements (no import is executed): the test
that imports run one way (cli → pipeline → {frontend, estimator} → core) reads the graph through this."""
from __future__ import annotations

import ast
import functools
import importlib.util
from pathlib import Path

ROOT_PACKAGE = "calib"


@functools.cache
def _source(name):
    """Path of module/package ``name``'s source file, or None when it is not a calib module."""
    if name != ROOT_PACKAGE and not name.startswith(ROOT_PACKAGE + "."):
        return None
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    return spec.origin if spec is not None and spec.origin and spec.origin.endswith(".py") else None


@functools.cache
def _parsed(path):
    """A source file's import statements, ((module or None for ``import``, level, names), ...), and its
    literal ``EXPORTS`` dict ({} if none: ``calib.lazy``)."""
    tree = ast.parse(Path(path).read_text(), filename=path)
    imports = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imports.append((None, 0, tuple(a.name for a in node.names)))
        elif isinstance(node, ast.ImportFrom):
            imports.append((node.module or "", node.level, tuple(a.name for a in node.names)))
    exports = next((ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
                    and any(getattr(t, "id", None) == "EXPORTS" for t in node.targets)), {})
    return tuple(imports), exports


def lazy_exports_of(package):
    """{name: submodule} of a package that loads its names lazily (``EXPORTS`` in its ``__init__``), else {}."""
    path = _source(package)
    return _parsed(path)[1] if path is not None and path.endswith("__init__.py") else {}


def imported_modules(name, path):
    """The calib modules named by the import statements of ``name`` (source at ``path``), anywhere in
    the file (function-level imports included). ``from pkg import sub`` counts ``pkg.sub`` when that
    is a module, the submodule behind ``sub`` when ``pkg`` loads it lazily, else ``pkg``."""
    package = name if Path(path).name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for module, level, names in _parsed(str(path))[0]:
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
