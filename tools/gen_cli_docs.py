"""Write docs/cli.md, the command-line reference, from the CLI itself: the --help of every `triswarm`
command and subcommand and of `triswarm-companion`, as a user sees it.

    python tools/gen_cli_docs.py            # rewrite docs/cli.md (make docs)
    python tools/gen_cli_docs.py --check    # exit 1 if docs/cli.md is not what the CLI says

Run it with the project's environment (.venv/bin/python). It uses only typer, which the CLI is
built on: typer.main.get_command for the command tree and typer.testing.CliRunner for the help.
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer
from typer.main import get_command
from typer.testing import CliRunner

from triswarm.companion.cli import app as companion_app
from triswarm.gcs.cli import app as gcs_app

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "cli.md"
WIDTH = 100  # fixed, so the file does not depend on the terminal it was made in

HEADER = """\
# Command-line reference

Generated from the CLI itself by `make docs` (`tools/gen_cli_docs.py`); do not edit by hand.
Every section is the command's `--help`. The guides explain what the commands do:
[ground station](ground-station.md), [companion](companion.md), [simulated flight
controllers](sitl.md), [simulated time](simulation.md), [deploy](../deploy/README.md).
"""


def commands(app: typer.Typer, prog: str) -> list[list[str]]:
    """Every command path under `prog`, groups before their subcommands, in the CLI's own order."""
    out: list[list[str]] = []

    def walk(cmd, path: list[str]) -> None:
        out.append(path)
        for name, sub in getattr(cmd, "commands", {}).items():
            if not getattr(sub, "hidden", False):
                walk(sub, path + [name])

    walk(get_command(app), [prog])
    return out


def help_text(app: typer.Typer, path: list[str]) -> str:
    result = CliRunner().invoke(app, path[1:] + ["--help"], prog_name=path[0], terminal_width=WIDTH,
                                max_content_width=WIDTH, catch_exceptions=False)
    if result.exit_code != 0:
        raise SystemExit(f"{' '.join(path)} --help exited {result.exit_code}:\n{result.output}")
    # Defaults computed from where this checkout lies (deploy --source) are not part of the reference.
    return result.output.replace(str(ROOT), "<this checkout>").rstrip() + "\n"


def render() -> str:
    sections = [(app, path) for app, prog in ((gcs_app, "triswarm"), (companion_app, "triswarm-companion"))
                for path in commands(app, prog)]
    toc = "".join(f"- [`{' '.join(p)}`](#{'-'.join(p)})\n" for _, p in sections)
    body = "".join(f"\n## {' '.join(p)}\n\n```text\n{help_text(app, p)}```\n" for app, p in sections)
    return f"{HEADER}\n{toc}{body}"


def main(argv: list[str]) -> int:
    text = render()
    if "--check" in argv:
        if not OUT.exists() or OUT.read_text(encoding="utf-8") != text:
            print(f"{OUT.relative_to(ROOT)} is out of date: run make docs", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    print(f"wrote {OUT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
