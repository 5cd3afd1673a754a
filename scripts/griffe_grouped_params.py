"""Griffe extension for the API reference: grouped parameters in Google-style docstrings.

jaxrt's docstrings document parameters that go together on one line (``width, height: image size``). The
Google-style parser of griffe reads one name per entry and would report ``width, height`` as an unknown
parameter; this extension rewrites such an entry, in ``Args:`` sections only, into one entry per name with the
same description before the docstring is parsed, so that every name is still checked against the signature.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_SECTION = re.compile(r"^(\s*)(Args|Arguments|Parameters|Params|Other Parameters):\s*$")
_GROUPED = re.compile(r"^(\s+)([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)+)\s*:(.*)$")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def split_grouped_parameters(text: str) -> str:
    """``text`` with every grouped entry of its ``Args:`` sections split into one entry per name."""
    lines = text.splitlines()
    out: list[str] = []
    section_indent: int | None = None
    i = 0
    while i < len(lines):
        line = lines[i]
        header = _SECTION.match(line)
        if header:
            section_indent = len(header.group(1))
        elif line.strip() and section_indent is not None and _indent(line) <= section_indent:
            section_indent = None  # the next section (or the end of this one)
        grouped = _GROUPED.match(line) if section_indent is not None else None
        if grouped:
            indent, names, description = grouped.groups()
            block = [lines[i]]
            while i + 1 < len(lines) and (not lines[i + 1].strip() or _indent(lines[i + 1]) > len(indent)):
                if not lines[i + 1].strip() and (i + 2 >= len(lines) or _indent(lines[i + 2]) <= len(indent)):
                    break
                i += 1
                block.append(lines[i])
            for name in (n.strip() for n in names.split(",")):
                out.append(f"{indent}{name}:{description}")
                out.extend(block[1:])
        else:
            out.append(line)
        i += 1
    return "\n".join(out)


class GroupedParameters(griffe.Extension):
    """Splits grouped parameter entries of every docstring as it is loaded."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = split_grouped_parameters(obj.docstring.value)
