"""Packages whose public names load on first use (PEP 562), so ``calib --help`` does not pay for
imports it does not need (``calib.frontend``: scipy.signal, matplotlib).

Not for a name that equals one of the package's submodules (``calib.estimator.calibrate``): importing that
submodule rebinds the package attribute to the module, which a lazy name cannot undo.

A package lists ``EXPORTS = {name: submodule}`` as a literal dict in its ``__init__`` (the import-direction
test, tests/modgraph.py, reads that dict to follow a name to its submodule).
"""
from __future__ import annotations

import importlib
import sys


def lazy_exports(package, exports):
    """(``__getattr__``, ``__dir__``) for package ``package`` whose names live in its submodules."""

    def __getattr__(name):
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{exports[name]}"), name)
        setattr(sys.modules[package], name, value)  # later lookups skip __getattr__
        return value

    def __dir__():
        return sorted(set(exports) | set(vars(sys.modules[package])))

    return __getattr__, __dir__
