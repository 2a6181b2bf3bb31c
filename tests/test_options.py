"""The estimator options are declared once (calib.estimator.options): the library check, the CLI flags, the
CLI's input check, the stage key's settings and docs/cli.md all derive from that table."""
import inspect
import math
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from calib.cli.main import app
from calib.errors import InputError
from calib.estimator.calibrate import calibrate, calibrate_features
from calib.estimator.clockmodel import calibrate_clocks
from calib.options import DEFAULTS, INPUTS, OPTIONS, cli_options, validate_options
from calib.pipeline.formats.validate import estimate_options
from calib.pipeline.run import estimate_defaults

OPTION_NAMES = [o.name for o in OPTIONS]
DOCS = Path(__file__).resolve().parents[1] / "docs" / "cli.md"


def test_calibrate_takes_every_option_with_its_declared_default():
    # ``calibrate`` is calibrate_clocks (the clock model's choice) around calibrate_features (the rest)
    params = {n: p for f in (calibrate_features, calibrate_clocks, calibrate) for n, p in inspect.signature(f).parameters.items()
              if p.kind is inspect.Parameter.KEYWORD_ONLY}
    assert set(params) == set(OPTION_NAMES) | set(INPUTS)
    for o in OPTIONS:
        assert params[o.name].default == o.default and isinstance(o.default, o.kind)
        o.check(o.default)
    assert estimate_defaults() == {o.name: DEFAULTS[o.name] for o in cli_options()}


@pytest.mark.parametrize("o", OPTIONS, ids=lambda o: o.name)
def test_library_and_cli_refuse_what_the_table_refuses(o):
    bad = (["nope", 3] if o.choices else ["yes", 1] if o.kind is bool else
           [math.nan, math.inf, o.lo - 1.0] + ([o.hi * 2] if math.isfinite(o.hi) else []))
    for v in bad:
        with pytest.raises(ValueError, match=o.name):
            validate_options(**{o.name: v})
        if o.flag:
            with pytest.raises(InputError, match=o.name.replace("_", "-") if o.kind is float else o.name):
                estimate_options({o.name: v})
    with pytest.raises(TypeError):
        validate_options(no_such_option=1)


@pytest.mark.parametrize("command", ["estimate", "run"])
def test_docs_cli_md_shows_each_flag_as_help_does(command):
    """docs/cli.md's `calib estimate` / `calib run` blocks carry the table's help text and defaults."""
    help_text = CliRunner().invoke(app, [command, "--help"], terminal_width=110).output
    block = DOCS.read_text().split(f"Usage: calib {command} ", 1)[1].split("```", 1)[0]
    squeeze = lambda text: re.sub(r"\s+", "", text)  # noqa: E731 (line wrapping depends on the terminal)
    for o in cli_options():
        entry = re.search(rf"^  {o.flag}\b.*?(?=^  -)", help_text, re.S | re.M)
        assert entry and " ".join(o.help.split()[:4]) in entry.group(0)
        # the flag and its help text (the rendering around them, e.g. a metavar, varies with typer's version)
        assert o.flag in block and squeeze(o.help) in squeeze(block), \
            f"docs/cli.md: update `calib {command} --help` ({o.flag}):\n{help_text}"
