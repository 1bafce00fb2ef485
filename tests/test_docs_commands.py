"""Every `ms-drake ...` command in the README and the docs pages names a command and options the CLI
has (parsed, not run): a renamed or removed option cannot survive in the documentation."""

import re
import shlex
from pathlib import Path

import pytest
import typer

from ms_drake.cli import app

ROOT = Path(__file__).resolve().parents[1]
# the README and the pages (the pre-registrations in docs/prereg are dated records of their time)
FILES = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if "prereg" not in p.parts)]
COMMAND = re.compile(r"(?:^|`|\s)(ms-drake [^`\n#]*)", re.M)
PLACEHOLDERS = {"...", "NAME", "COMMAND"}


def commands(text: str) -> list[str]:
    """The ms-drake command lines of a page, continuation lines (a trailing backslash) joined."""
    return [m.group(1).strip() for m in COMMAND.finditer(re.sub(r"\\\n\s*", " ", text))]


def problems(line: str, root) -> list[str]:
    """What in one command line the CLI does not have: a subcommand or an option."""
    try:
        args = shlex.split(line)[1:]
    except ValueError:  # an unterminated quote: prose around a command, not a command
        return []
    command = root
    while getattr(command, "commands", None) and args and args[0] in command.commands:
        command = command.commands[args.pop(0)]
    if getattr(command, "commands", None):
        return [f"no command {args[0]!r}"] if args and not args[0].startswith("-") and args[0] not in PLACEHOLDERS \
            else []
    options = {o for p in command.params for o in (*p.opts, *p.secondary_opts)} | {"--help"}
    return [f"unknown option {a.split('=')[0]}" for a in args if a.startswith("--") and a.split("=")[0] not in options]


def test_the_checker_finds_a_bad_option_and_command():
    root = typer.main.get_command(app)
    assert problems("ms-drake bench search --protocol xray --policy xray", root) == ["unknown option --protocol"]
    assert problems("ms-drake bench serch --policy xray", root) == ["no command 'serch'"]
    assert problems("ms-drake bench shelf --policy dar --set ablation.suction_lift=floor", root) == []
    assert shlex.split(commands("run `ms-drake demo \\\n    --out D` then")[0]) == ["ms-drake", "demo", "--out", "D"]


@pytest.mark.parametrize("page", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_documented_commands_exist(page):
    root = typer.main.get_command(app)
    bad = [(line[:120], p) for line in commands(page.read_text()) for p in problems(line, root)]
    assert not bad, bad
