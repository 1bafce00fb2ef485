"""A griffe extension (mkdocs.yml, the python handler's `extensions`): the package's docstrings are
plain text laid out for a terminal; this turns them into markdown that shows the same.

Per paragraph (blank-line separated): lines indented under a first line (diagrams, aligned port
lists, commands) become a fenced text block after it; a "- " list gets the blank line markdown
wants before it; elsewhere `<` outside code spans is escaped, so `<cam>.rgb_image` is not taken
for an HTML tag.
"""

from __future__ import annotations

import re
import textwrap

import griffe

CODE_SPAN = re.compile(r"(``.+?``|`[^`]+`)")


def _escape(line: str) -> str:
    parts = CODE_SPAN.split(line)
    return "".join(p if i % 2 else p.replace("<", "&lt;") for i, p in enumerate(parts))


def _fence(lines: list[str]) -> list[str]:
    return ["```text", *textwrap.dedent("\n".join(lines)).splitlines(), "```"]


def _paragraph(lines: list[str]) -> list[str]:
    if all(line.startswith("    ") for line in lines):  # already a markdown code block
        return lines
    if any(line.startswith(("- ", "* ")) for line in lines):
        first = next(i for i, line in enumerate(lines) if line.startswith(("- ", "* ")))
        head = [_escape(line) for line in lines[:first]]
        return head + ([""] if head else []) + [_escape(line) for line in lines[first:]]
    indented = next((i for i, line in enumerate(lines) if line.startswith(" ")), None)
    if indented is None:
        return [_escape(line) for line in lines]
    return [_escape(line) for line in lines[:indented]] + ([""] if indented else []) + _fence(lines[indented:])


def to_markdown(text: str) -> str:
    """A plain-text docstring as markdown (see the module docstring)."""
    out, block, fenced = [], [], False
    for line in text.splitlines() + [""]:
        if line.lstrip().startswith("```"):
            fenced = not fenced
        if fenced or line.lstrip().startswith("```"):
            out.extend(_paragraph(block) if block else [])
            block = []
            out.append(line)
        elif line.strip():
            block.append(line.rstrip())
        else:
            out.extend(_paragraph(block) if block else [])
            out.append("")
            block = []
    return "\n".join(out).rstrip() + "\n"


class PlainDocstrings(griffe.Extension):
    """Every docstring of the loaded package through `to_markdown`."""

    def on_instance(self, *, node, obj, agent, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = to_markdown(obj.docstring.value)
