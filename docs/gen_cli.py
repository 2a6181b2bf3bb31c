"""Regenerate the `--help` blocks of docs/cli.md from the CLI itself (tests/test_docs.py checks they are equal).

    python docs/gen_cli.py            # rewrite docs/cli.md in place
    python docs/gen_cli.py --check    # exit 1 if docs/cli.md differs from the CLI's help

Each ``## `calib CMD` `` heading of docs/cli.md is followed by one fenced block: the output of
``calib CMD --help`` at 110 columns (the CLI's max_content_width).
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

CLI_MD = Path(__file__).resolve().parent / "cli.md"
WIDTH = 110
SECTION = re.compile(r"(## `calib ([a-z-]+)`\n\n```\n)(.*?)(^```$)", re.S | re.M)  # an empty block too


def help_text(command):
    """``calib COMMAND --help`` as a user sees it at WIDTH columns."""
    from typer.testing import CliRunner

    from calib.cli.main import app

    r = CliRunner().invoke(app, [command, "--help"], terminal_width=WIDTH, prog_name="calib")
    if r.exit_code != 0:
        raise RuntimeError(f"calib {command} --help: exit {r.exit_code}\n{r.output}")
    return r.stdout.rstrip("\n")


def render(text):
    """docs/cli.md's text with every command's block replaced by its current help."""
    return SECTION.sub(lambda m: m.group(1) + help_text(m.group(2)) + "\n" + m.group(4), text)


def main(argv):
    text = CLI_MD.read_text()
    new = render(text)
    if "--check" in argv:
        if new != text:
            print(f"{CLI_MD}: out of date (python docs/gen_cli.py)", file=sys.stderr)
            return 1
        return 0
    CLI_MD.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
