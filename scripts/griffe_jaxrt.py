"""Griffe extension for the API reference: jaxrt's docstring conventions in Google-style Markdown.

- **Grouped parameters.** Parameters that go together share one entry (``width, height: image size``). The
  Google-style parser of griffe reads one name per entry and would report ``width, height`` as an unknown
  parameter; such an entry, in ``Args:`` sections only, becomes one entry per name with the same description,
  so that every name is still checked against the signature.
- **Sphinx roles.** ``:class:`~jaxrt.Ray```, ``:func:`load_hair``` and the like become code that links to the
  named object where the reference documents it (an optional cross-reference: private or unknown targets stay
  plain code, never a broken link). A bare name is looked up in the docstring's own module first.

Both rewrite the docstring text before it is parsed.

- **The kinds' public names.** ``rt.IntersectionType`` and the kinds' tags in ``rt.tags`` are built at import
  from the kind registry (one member and its tags per kind), so the source the reference is read from does not
  list them: the enum is documented as the class it is, with one member per kind, and each kind's tag as an
  attribute of ``jaxrt.tags``, with the docstrings the kinds declare.

- **Plumbing.** Special methods (``__repr__``, ``__new__``, ...; ``__init__``, merged into its class's entry,
  and ``__call__`` stay) and the pytree protocol
  (``tree_flatten``, ``tree_unflatten``) of the public classes are left out of the reference.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:func|class|mod|data|meth|attr|exc|obj):`(~?)([\w.]+)`")
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


def replace_roles(text: str, module: str = "", owner: str = "") -> str:
    """``text`` with Sphinx cross-reference roles turned into optional autorefs around code spans.

    A bare name is looked up as a member of ``owner`` (the class of a method's docstring) first, then of
    ``module`` (``load_hair`` in ``jaxrt._src.io.hair`` is ``jaxrt._src.io.hair.load_hair``).
    """

    def link(match: re.Match) -> str:
        short, target = match.groups()
        title = target.rsplit(".", 1)[-1] if short else target
        scopes = [scope for scope in (owner, module) if scope] if "." not in target else []
        candidates = [f"{scope}.{target}" for scope in scopes] or [target]
        slug = f' slug="{candidates[1]}"' if len(candidates) > 1 else ""
        return f'<autoref identifier="{candidates[0]}"{slug} optional><code>{title}</code></autoref>'

    return _ROLE.sub(link, text)


PLUMBING = frozenset(["tree_flatten", "tree_unflatten"])


def is_plumbing(name: str) -> bool:
    """Whether a class member is left out of the reference (special methods, pytree protocol)."""
    special = name.startswith("__") and name.endswith("__") and name not in ("__init__", "__call__")
    return special or name in PLUMBING


def _attribute(name: str, value: str, doc: str, label: str) -> griffe.Attribute:
    attribute = griffe.Attribute(name, value=value)
    attribute.docstring = griffe.Docstring(replace_roles(doc), parent=attribute)
    attribute.labels.add(label)
    return attribute


def add_kind_names(mod: griffe.Module) -> None:
    """Document what the kind registry adds at import: the members of ``IntersectionType`` (in
    ``jaxrt._src.result``) and the kinds' tags (in ``jaxrt.tags``)."""
    if mod.path not in ("jaxrt.tags", "jaxrt._src.result"):
        return
    from jaxrt import tags
    from jaxrt._src import result
    from jaxrt._src.kinds import registry

    if mod.path == "jaxrt.tags":
        for name, doc in tags.KIND_TAG_DOCS.items():
            mod.set_member(name, _attribute(name, f'Tag("{name}")', doc, "module-attribute"))
            if mod.exports is not None and name not in mod.exports:
                mod.exports.append(name)
        return
    old = mod.members["IntersectionType"]
    cls = griffe.Class("IntersectionType", lineno=old.lineno, endlineno=old.endlineno, bases=["enum.IntEnum"])
    cls.docstring = griffe.Docstring(
        "What a ray hit (Metal's ``intersection_type``): ``NONE``, or the kind of the hit primitive (one member "
        "per kind of the kind registry).",
        parent=cls,
    )
    docs = {"NONE": result.NONE_DOC, **{k.name.upper(): k.doc for k in registry.KINDS}}
    for member in result.IntersectionType:
        cls.set_member(member.name, _attribute(member.name, str(member.value), docs[member.name], "class-attribute"))
    mod.set_member("IntersectionType", cls)


class JaxrtDocstrings(griffe.Extension):
    """Rewrites every docstring as it is loaded (grouped parameters split, Sphinx roles as links), drops
    the plumbing members of classes and documents the names the kind registry adds."""

    def on_module_members(self, *, mod: griffe.Module, **kwargs: Any) -> None:
        add_kind_names(mod)

    def on_class_members(self, *, cls: griffe.Class, **kwargs: Any) -> None:
        for name in [name for name in cls.members if is_plumbing(name)]:
            cls.del_member(name)

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            module = obj.path if obj.is_module else obj.module.path
            owner = obj.path if obj.is_class else (obj.parent.path if obj.parent and obj.parent.is_class else "")
            text = split_grouped_parameters(obj.docstring.value)
            obj.docstring.value = replace_roles(text, module, owner)
