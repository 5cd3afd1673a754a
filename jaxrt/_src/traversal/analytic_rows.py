"""The compiled loops' leaf dispatch over analytic rows, generated from the kind registry.

The GPU kernel and the CPU traversal test two sorts of leaves by an analytic row
(:func:`jaxrt._src.traversal.packed.pack_analytic`: ``p``, the shape code, ``q``, ``radius``): the bounding
boxes of the built-in intersection functions (codes 1-3, :mod:`jaxrt._src.formulas.analytic`) and the leaves of
every kind that declares an :class:`~jaxrt._src.kinds.kind.AnalyticRow` (spheres, code 5), whose formula alone
decides a hit. The dispatch that picks each leaf's test by its code is written here once, as source text over
:data:`SHAPES` (the built-in shapes, then :data:`ROW_KINDS` in code order), and compiled by each loop at import:
:func:`jaxrt._src.traversal.triton_analytic.analytic_hit` for Triton, ``_analytic`` and ``_formula_row`` of
:mod:`jaxrt._src.traversal.cpu_kernel` for Numba. A kind added to the registry with an ``analytic`` record is
traced by both loops without an edit there.

For the kinds the library ships, the generated functions are the hand-written ones they replace, statement for
statement (the same branches on the same compile-time bits, the same calls), so the compiled code is the same.
The source is registered in :mod:`linecache` (Triton reads a jit function's source with :mod:`inspect`;
tracebacks show the generated lines), and :data:`SOURCE_DIGEST` keys the caches of compiled code that embed it.
"""

from __future__ import annotations

import hashlib
import linecache
import sys
import types
from typing import NamedTuple

from jaxrt._src.kinds import registry
from jaxrt._src.kinds.kind import ROW_COLUMNS, Kind

__all__ = [
    "ANALYTIC_SHAPES",
    "FORMULA_SHAPES",
    "ROW_KINDS",
    "SHAPES",
    "SOURCE_DIGEST",
    "Shape",
    "compile_source",
    "numba_source",
    "shape_bit",
    "triton_source",
]


class Shape(NamedTuple):
    """One test of the dispatch: the leaves of shape ``code`` call ``formula.test`` on the row's ``columns``."""

    code: int
    formula: str
    test: str
    columns: tuple[str, ...]
    results: int


#: The built-in intersection functions' shapes (sphere, disk, capped cylinder), as the bounding-box kind's
#: leaves carry them.
_BUILTIN = (
    Shape(1, "analytic", "sphere", ("px", "py", "pz", "radius"), 2),
    Shape(2, "analytic", "disk", ROW_COLUMNS, 2),
    Shape(3, "analytic", "capped_cylinder", ROW_COLUMNS, 2),
)
#: The kinds whose leaves the compiled loops test as analytic rows, in code order.
ROW_KINDS: tuple[Kind, ...] = tuple(
    sorted((k for k in registry.KINDS if k.analytic is not None), key=lambda k: k.analytic.code)
)
#: Every shape of the dispatch: the built-in functions', then the kinds'.
SHAPES: tuple[Shape, ...] = (
    *_BUILTIN,
    *(Shape(r.code, r.formula, r.test, r.columns, r.results) for r in (k.analytic for k in ROW_KINDS)),
)


def shape_bit(code: int) -> int:
    """The bit of the loops' ``shapes`` that says a scene holds leaves of shape ``code``: ``code - 1`` for the
    built-in functions (1-3), ``code`` from 4 on (bit 3 says triangles)."""
    return code - 1 if code <= 3 else code


#: The bits of the kinds' shapes (:data:`ROW_KINDS`) in ``shapes``.
FORMULA_SHAPES = sum(1 << shape_bit(k.analytic.code) for k in ROW_KINDS)
#: The bits of every shape of the dispatch: the built-in functions' (0-2) and the kinds'.
ANALYTIC_SHAPES = 7 | FORMULA_SHAPES


def _check() -> None:
    codes = [s.code for s in SHAPES]
    if len(set(codes)) != len(codes) or any(k.analytic.code < 5 for k in ROW_KINDS):
        raise ValueError(f"analytic_rows: the kinds' row codes must be distinct and >= 5, got {codes}")
    for s in SHAPES:
        if not set(s.columns) <= set(ROW_COLUMNS) or s.results < 2:
            raise ValueError(f"analytic_rows: shape {s.code} reads columns {s.columns} or returns {s.results}")


_check()


def _name(shape: Shape) -> str:
    """The dispatch's name for a shape's test."""
    return f"_{shape.formula}_{shape.test}"


def _targets(shape: Shape) -> str:
    return "h, t" + ", _" * (shape.results - 2)


_TRITON_RAY = "ox, oy, oz, dx, dy, dz, t_min, t_max"


def triton_source(shapes: tuple[Shape, ...] = SHAPES) -> str:
    """The source of ``analytic_hit`` (the kernel's leaf test of analytic rows) over ``shapes``."""
    lines = [
        "@triton.jit",
        "def analytic_hit(",
        "    code, mask, px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max, ANALYTIC: tl.constexpr",
        "):  # fmt: skip",
        '    """``(hit, distance)`` of analytic leaves where ``mask`` (``inf`` where not hit): each lane\'s shape by',
        "    its ``code``. ``SHAPES``, the bits of the shapes (``shape_bit``) in the kernel's compile-time ``ANALYTIC``",
        "    (which also has bits for triangles and candidate boxes), says which shapes the scene holds: only those",
        '    are compiled, and with several each is computed only where some lane of the warp needs it."""',
        f"    SHAPES: tl.constexpr = ANALYTIC & {ANALYTIC_SHAPES}",
        "    hit = tl.zeros(mask.shape, tl.int1)",
        '    distance = tl.full(mask.shape, float("inf"), tl.float32)',
    ]
    for shape in shapes:
        call = f"{_targets(shape)} = {_name(shape)}({', '.join(shape.columns)}, {_TRITON_RAY})"
        lines += [
            f"    if (SHAPES & {1 << shape_bit(shape.code)}) != 0:",
            f"        lanes = mask & (code == {float(shape.code)})",
            "        if (SHAPES & (SHAPES - 1)) != 0:",
            "            if _any(lanes):",
            f"                {call}",
            "                hit, distance = _merge(hit, distance, lanes & h, t)",
            "        else:",
            f"            {call}",
            "            hit, distance = _merge(hit, distance, lanes & h, t)",
        ]
    lines.append('    return hit, tl.where(hit, distance, float("inf"))')
    return "\n".join(lines) + "\n"


#: Where each row column lies in a row of 12 (:func:`jaxrt._src.traversal.packed.pack_analytic`).
_COLUMN = {"px": 0, "py": 1, "pz": 2, "qx": 4, "qy": 5, "qz": 6, "radius": 7}
_NUMBA_RAY = "ox, oy, oz, dx, dy, dz, t_min, t_max"


def _branches(shapes: tuple[Shape, ...], read, indent: str) -> list[str]:
    """An ``if code == ...`` chain over ``shapes`` whose last one is the ``else`` (one shape: no test)."""
    lines = []
    for i, shape in enumerate(shapes):
        call = f"{_targets(shape).replace('h, t', 'ok, t')} = {_name(shape)}({', '.join(read(c) for c in shape.columns)}, {_NUMBA_RAY})"  # noqa: E501
        if len(shapes) == 1:
            return [f"{indent}{call}"]
        head = "if" if i == 0 else "elif"
        lines += [f"{indent}{head} code == {shape.code}:" if i < len(shapes) - 1 else f"{indent}else:"]
        lines.append(f"{indent}    {call}")
    return lines


def numba_source(shapes: tuple[Shape, ...] = SHAPES) -> str:
    """The source of the CPU loop's dispatch over ``shapes`` (the built-in functions', then the kinds'):
    ``analytic`` (any analytic row, the kinds' shapes first) and, for the lean loop of triangles and the kinds' leaves,
    ``is_formula_row`` and ``formula_row`` (a row of flat analytic rows at offset ``a``). The offsets ``_U1`` to
    ``_U7`` are the loop's unsigned constants."""
    kinds = shapes[len(_BUILTIN) :]
    row = lambda c: f"row[{_COLUMN[c]}]"  # noqa: E731
    flat = lambda c: "af[a]" if _COLUMN[c] == 0 else f"af[a + _U{_COLUMN[c]}]"  # noqa: E731
    lines = [
        "def analytic(row, ox, oy, oz, dx, dy, dz, t_min, t_max, one, inf):",
        '    """``(accepted, distance)`` of an analytic leaf\'s row (``p``, code, ``q``, radius) for the ray of its',
        '    level."""',
        "    code = row[3]",
        *_branches((*kinds, *_BUILTIN), row, "    "),
        "    return ok, (t if ok else inf)",
        "",
        "",
        "def is_formula_row(code):",
        '    """Whether shape ``code`` is a kind\'s (:data:`ROW_KINDS`), whose row the lean loop tests."""',
        "    return " + (" or ".join(f"code == {s.code}" for s in kinds) or "False"),
        "",
        "",
        "def formula_row(af, a, ox, oy, oz, dx, dy, dz, t_min, t_max, inf):",
        '    """``(hit, distance)`` of the kind\'s row at offset ``a`` of the flat rows ``af`` (the distance is the',
        '    formula\'s also without a hit)."""',
    ]
    if len(kinds) > 1:
        lines.append("    code = af[a + _U3]")
    if kinds:
        lines += _branches(kinds, flat, "    ")
    else:
        lines += ["    ok, t = False, inf"]
    lines += ["    return ok, t"]
    return "\n".join(lines) + "\n"


#: A digest of the generated sources, for caches of compiled code that embeds them.
SOURCE_DIGEST = hashlib.sha256((triton_source() + numba_source()).encode()).hexdigest()


def compile_source(name: str, source: str, namespace: dict, shapes: tuple[Shape, ...] = SHAPES) -> types.ModuleType:
    """Execute generated ``source`` in a fresh module ``jaxrt._src.traversal.analytic_rows.<name>`` holding
    ``namespace`` (the names it calls) and the shapes' tests under :func:`_name`'s names (taken from
    ``namespace["tests"]``: ``(formula, test) -> function``); its source is registered in :mod:`linecache`."""
    filename = f"<jaxrt.analytic_rows:{name}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    module = types.ModuleType(f"{__name__}.{name}")
    module.__file__ = filename
    tests = namespace.pop("tests")
    module.__dict__.update(namespace)
    for shape in shapes:
        setattr(module, _name(shape), tests(shape.formula, shape.test))
    sys.modules[module.__name__] = module  # Triton looks functions' modules up by name
    exec(compile(source, filename, "exec"), module.__dict__)
    return module
