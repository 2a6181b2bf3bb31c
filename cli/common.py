"""Shared CLI plumbing: one-line errors with exit code 2, internal errors, interrupts, consoles.

Exit codes (docs/reliability.md): 0 ok, 1 internal error (a bug: the traceback is written to a file
whose path is printed), 2 bad input (``error: <file>: <problem>``), 3 a calibration whose verdict is
"failed" (everything is still written), 130 SIGINT, 143 SIGTERM.
"""
from __future__ import annotations

import datetime
import functools
import inspect
import os
import sys
import tempfile
import traceback
import warnings
from typing import Annotated

import typer
from rich.console import Console

from calib.errors import InputError, InputWarning
from calib.pipeline.formats import validate as V
from calib.pipeline.formats.outputs import ENVIRONMENT_ERRNOS

from . import signals
from .signals import EXIT_FAILED, EXIT_INPUT, EXIT_INTERNAL  # noqa: F401  (re-exported)

console = Console(stderr=True)
MAX_WARNINGS = 5  # input warnings printed per command; the rest are counted in one line


def _one_line(text):
    return " ".join(str(text).split())


def _report_bug(exc):
    """Write the traceback to a file in the temp folder; return its path."""
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    path = os.path.join(tempfile.gettempdir(), f"calib-internal-error-{stamp}-{os.getpid()}.txt")
    try:
        with open(path, "w") as f:
            f.write(f"calib {' '.join(sys.argv[1:])}\n\n")
            traceback.print_exception(exc, file=f)
    except OSError:
        return None
    return path


class _Warnings:
    """Show InputWarnings as ``warning: <file>: <problem>`` lines (at most MAX_WARNINGS, then a count)."""

    def __init__(self):
        self.seen = []
        self.other = warnings.showwarning  # warnings of other kinds are shown as Python shows them

    def show(self, message, category, filename, lineno, file=None, line=None):
        if not issubclass(category, InputWarning):
            self.other(message, category, filename, lineno, file, line)
            return
        text = _one_line(message)
        if text in self.seen:
            return
        self.seen.append(text)
        if len(self.seen) <= MAX_WARNINGS:
            print(f"warning: {text}", file=sys.stderr)

    def summary(self):
        if len(self.seen) > MAX_WARNINGS:
            print(f"warning: {len(self.seen) - MAX_WARNINGS} more warning(s) not shown", file=sys.stderr)


def user_errors(func):
    """Run a command with the project's error policy.

    InputError (bad input) and OSErrors of the environment (full disk, read-only folder, over-long name)
    → ``error: <one line>`` on stderr, exit 2. KeyboardInterrupt / SIGTERM → one line, exit 130 / 143.
    Anything else is a bug → ``internal error`` with the traceback in a file, exit 1.
    """

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        previous = signals.install()
        shown = _Warnings()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("always", InputWarning)
                warnings.showwarning = shown.show
                result = func(*args, **kwargs)
            shown.summary()
            return result
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except InputError as exc:
            print(f"error: {_one_line(exc)}", file=sys.stderr)
            raise typer.Exit(EXIT_INPUT) from None
        except OSError as exc:
            if exc.errno not in ENVIRONMENT_ERRNOS:
                _internal(exc)
            where = exc.filename if exc.filename is not None else "output"
            print(f"error: {where}: {_one_line(exc.strerror or exc)}", file=sys.stderr)
            raise typer.Exit(EXIT_INPUT) from None
        except KeyboardInterrupt as exc:
            raise typer.Exit(signals.interrupted(exc)) from None
        except Exception as exc:  # a bug in calib, not bad input
            _internal(exc)
        finally:
            signals.restore(previous)

    return wrapper


def waiting(message):
    """``on_wait`` of the output lock: say why the command pauses."""
    print(f"waiting: {message}", file=sys.stderr)


def _internal(exc):
    path = _report_bug(exc)
    where = f"traceback written to {path}" if path else "no traceback file could be written"
    print(f"internal error: {type(exc).__name__}: {_one_line(exc)[:200]} (a bug in calib; {where}; please report "
          "it)", file=sys.stderr)
    raise typer.Exit(EXIT_INTERNAL) from None


Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="print nothing but errors")]
Jobs = Annotated[int, typer.Option("--jobs", "-j", help="arrays whose features are extracted at a time, in threads "
                                   "(-1: one per core); the results do not depend on it")]


def _estimate_params():
    """The typer parameters of the estimator options (``calib.estimator.options``: flag, help, default)."""
    from calib.options import cli_options

    params = []
    for o in cli_options():
        name = o.flag[2:].replace("-", "_")  # the bool flag's own name (no_tdoa_s)
        decl = typer.Option(o.flag, help=o.help) if o.kind is bool else typer.Option(help=o.help)
        default = False if o.kind is bool else o.default  # a bool's flag is a switch: given or not
        params.append(inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                        annotation=Annotated[o.kind, decl], default=default))
    return params


def estimate_options(values):
    """Validated keyword arguments of ``estimator.calibrate`` from the shared CLI options (InputError)."""
    from calib.options import cli_options

    # a bool's switch, when given, flips the library default (--no-tdoa-s: use_tdoa_s=False)
    opts = {o.name: (o.default != v) if o.kind is bool else v for o, v in zip(cli_options(), values)}
    return V.estimate_options(opts)


def with_estimate_options(func):
    """Give a command the estimator options (one declaration for `calib estimate` and `calib run`).

    ``func`` declares a parameter ``est_opts``; the command shows the flagged options of
    ``calib.estimator.options.OPTIONS`` in its place and ``func`` receives them validated
    (:func:`estimate_options`; put it under ``user_errors``).
    """
    sig = inspect.signature(func, eval_str=True)  # (typer does not evaluate a __signature__'s strings)
    est = _estimate_params()
    names = [p.name for p in est]
    params = []
    for p in sig.parameters.values():
        params += est if p.name == "est_opts" else [p]

    @functools.wraps(func)
    def wrapper(**kwargs):
        values = [kwargs.pop(n) for n in names]
        return func(**kwargs, est_opts=estimate_options(values))

    wrapper.__signature__ = sig.replace(parameters=params)
    return wrapper


def print_verdict(report, console):
    """The verdict, last: status in capitals, then one line per reason (report.json ``verdict``)."""
    v = report.get("verdict") or {}
    status = str(v.get("status", "?"))
    colour = {"ok": "green", "suspect": "yellow", "failed": "bold red"}.get(status, "")
    flagged = v.get("flagged_arrays") or []
    extra = f" (flagged arrays: {', '.join(flagged)})" if flagged else ""
    console.print(f"verdict: [{colour}]{status.upper()}[/{colour}]{extra}" if colour else f"verdict: {status}")
    for r in v.get("reasons") or []:
        console.print(f"  - {r}", highlight=False)


def exit_on_failed(report):
    """Exit with EXIT_FAILED when the verdict is "failed" (after everything has been written and shown)."""
    if (report.get("verdict") or {}).get("status") == "failed":
        raise typer.Exit(EXIT_FAILED)


PLAIN_PROGRESS_EVERY_S = 5.0  # a log file gets a progress line at most this often (and the last one always)


class _PlainProgress:
    """``progress(done, total, message)`` as plain timestamped lines on stderr (``HH:MM:SS name: done/total
    message``): what a log file can hold, where a live bar writes nothing until it ends."""

    def __init__(self, name):
        self.name, self.last = name, None

    def __call__(self, done, total, msg=""):
        import time

        now = time.monotonic()
        final = total is not None and done >= total
        if self.last is not None and now - self.last < PLAIN_PROGRESS_EVERY_S and not final:
            return
        self.last = now
        count = f"{done}/{total}" if total else f"{done}"
        print(f"{datetime.datetime.now():%H:%M:%S} {self.name}: {count} {msg}".rstrip(), file=sys.stderr, flush=True)


def progress_display(name, remaining=False):
    """A context manager giving a long command's ``progress(done, total, message)`` callback: a rich bar when
    stderr is a terminal, else plain timestamped lines (:class:`_PlainProgress`). ``remaining``: the bar also
    shows the time left."""
    import contextlib

    @contextlib.contextmanager
    def display():
        if not console.is_terminal:
            yield _PlainProgress(name)
            return
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        cols = [TextColumn(name), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[msg]}"),
                TimeElapsedColumn()] + ([TimeRemainingColumn()] if remaining else [])
        with Progress(*cols, console=console) as bar:
            task = bar.add_task(name, total=None, msg="")
            yield lambda done, total, msg="": bar.update(task, total=total, completed=done, msg=msg)

    return display()
