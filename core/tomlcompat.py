"""TOML reading on every supported Python: the standard library's ``tomllib`` (3.11+), else ``tomli`` (the
package tomllib was taken from: the same API and parser; a dependency only where tomllib is missing)."""
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

__all__ = ["tomllib"]
