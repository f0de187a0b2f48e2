"""Write the command reference (docs/commands.md) from the ``hostlink`` argparse parsers, so the page says exactly
what ``hostlink COMMAND --help`` says.

    python scripts/gen_command_docs.py > docs/commands.md     # regenerate
    python scripts/gen_command_docs.py --check                # exit 1 if docs/commands.md is not current

tests/test_docs_pages.py runs the check. The usage lines are written here rather than by argparse, whose wrapping
depends on the terminal width and the Python version.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "commands.md"

if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

from hostlink.cli import COMMANDS, build_parser  # noqa: E402


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse keeps sub-commands in a _SubParsersAction; no public accessor
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise RuntimeError("hostlink's parser has no sub-commands")


def _help_lines(parser: argparse.ArgumentParser) -> dict[str, str]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return {a.dest: a.help or "" for a in action._choices_actions}
    return {}


def _metavar(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.metavar is not None:
        return str(action.metavar)
    if action.choices is not None:
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    return action.dest.upper() if action.option_strings else action.dest


def _usage_part(action: argparse.Action) -> str:
    if not action.option_strings:
        return _metavar(action)
    flag = max(action.option_strings, key=len)
    text = f"{flag} {_metavar(action)}".strip()
    return text if action.required else f"[{text}]"


def _name(action: argparse.Action) -> str:
    if not action.option_strings:
        return f"`{_metavar(action)}`"
    metavar = _metavar(action)
    return ", ".join(f"`{s} {metavar}`".replace(" `", "`") if metavar else f"`{s}`" for s in action.option_strings)


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _expand(action: argparse.Action, prog: str) -> str:
    text = action.help or ""
    if "%" in text:
        text = text % {**vars(action), "prog": prog}
    if action.choices is not None and action.metavar is not None:
        text += " (one of: " + ", ".join(str(c) for c in action.choices) + ")"
    return text


def render() -> str:
    """The whole page."""
    parser = build_parser()
    subs = _subparsers(parser)
    helps = _help_lines(parser)
    lines = [
        "# Command reference",
        "",
        "Generated from the `hostlink` argument parsers by `scripts/gen_command_docs.py` "
        "(`python scripts/gen_command_docs.py > docs/commands.md`); a test keeps it current. "
        "`hostlink COMMAND --help` prints the same. Link strings are in [links.md](links.md), file formats in "
        "[file-formats.md](file-formats.md), exit codes in [links.md](links.md#exit-codes).",
        "",
        "`hostlink --version` prints the installed version; `hostlink --help` lists the commands.",
        "",
        "| command | does |",
        "|---|---|",
    ]
    names = [n for n in COMMANDS if n in subs]
    lines += [f"| [`{n}`](#hostlink-{n}) | {_cell(helps.get(n, ''))} |" for n in names]
    for name in names:
        sub = subs[name]
        actions = [a for a in sub._actions if not isinstance(a, argparse._HelpAction)]
        usage = " ".join(["hostlink", name, *(_usage_part(a) for a in actions)])
        lines += ["", f"## hostlink {name}", "", _cell(sub.description or helps.get(name, "")), ""]
        lines += ["```", usage, "```", ""]
        lines += ["| argument | required | meaning |", "|---|---|---|"]
        for a in actions:
            required = "yes" if (a.required or not a.option_strings) else ""
            lines.append(f"| {_name(a)} | {required} | {_cell(_expand(a, sub.prog))} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args.add_argument("--check", action="store_true", help=f"exit 1 if {PAGE.relative_to(ROOT)} is not current")
    opts = args.parse_args(argv)
    text = render()
    if opts.check:
        current = PAGE.read_text(encoding="utf-8") if PAGE.exists() else ""
        if current != text:
            print(f"{PAGE.relative_to(ROOT)} is out of date: python scripts/gen_command_docs.py > docs/commands.md")
            return 1
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
