"""MkDocs hook: the API reference section, one page per public module of jaxrt.

The public modules are ``jaxrt`` and the submodules named in ``jaxrt.__all__`` (read from the source, without
importing jax). A module without a page in ``docs/reference/`` gets a generated one holding only the
mkdocstrings directive, and the "API reference" entry of the nav lists every page, ``jaxrt`` first. Public
names come from each module's ``__all__`` (``filters: public``), so new ones appear without editing the docs.
"""

from __future__ import annotations

import ast
from pathlib import Path

SECTION = "API reference"
ROOT = Path(__file__).resolve().parents[1]


def public_modules() -> list[str]:
    """``jaxrt`` and its submodules listed in ``jaxrt.__all__``, in that order."""
    tree = ast.parse((ROOT / "jaxrt" / "__init__.py").read_text())
    names: list[str] = []
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            names = list(ast.literal_eval(node.value))
    submodules = [
        n for n in names if (ROOT / "jaxrt" / f"{n}.py").is_file() or (ROOT / "jaxrt" / n / "__init__.py").is_file()
    ]
    return ["jaxrt"] + [f"jaxrt.{n}" for n in sorted(submodules)]


def _page(module: str) -> str:
    return f"reference/{module}.md"


def on_config(config):
    """Fill the empty "API reference" nav entry with one page per public module."""
    for entry in config["nav"] or []:
        if isinstance(entry, dict) and SECTION in entry and not entry[SECTION]:
            entry[SECTION] = [{module: _page(module)} for module in public_modules()]
            return config
    raise ValueError(f'mkdocs_reference: mkdocs.yml needs an empty "{SECTION}: []" entry in its nav')


def on_files(files, config):
    """Add a generated page for each public module that has no page in docs/reference/."""
    from mkdocs.structure.files import File

    for module in public_modules():
        if files.get_file_from_path(_page(module)) is None:
            content = f"# `{module}`\n\n::: {module}\n"
            files.append(File.generated(config, _page(module), content=content))
    return files
