"""Opt-in input checks of builds that also work on traced arrays (``checks=True``).

Geometry and :class:`~jaxrt.Instances` constructors validate concrete arrays on the host. Inside ``jax.jit``
their arrays are tracers: a NaN vertex, an index out of range or a singular transform then makes rays miss
without a word. With ``checks=True`` a build computes, on the device, a flag and the first offending element
of each rule, and hands them to one host callback (``jax.experimental.io_callback``) that raises
:class:`BuildCheckError` naming the function, the argument, the element and its value. With concrete arrays
it is raised directly.

Inside ``jit`` JAX wraps every exception a host callback raises into a ``jax.errors.JaxRuntimeError`` whose
message is the callback's traceback (when the computation runs, not when it is traced), and Python's
``except`` cannot match that by type. :func:`build_check_errors` raises it again as a :class:`BuildCheckError`
with the one-line message, so that ``except rt.BuildCheckError`` works around jitted code too::

    try:
        with rt.build_check_errors():
            structure = jax.block_until_ready(build(vertices))  # a jitted function with a checks=True build
    except rt.BuildCheckError as error:
        print(error)  # build_primitive_structure: geometries[0] (TriangleGeometry) vertices[0] = ...

Cost: one reduction per rule over the input arrays and one device-to-host synchronisation per build; off by
default. Measured on a shared 2-core CPU (jax 0.10.2, jitted builds, steady state): 10,000 triangles 4.2 ms
unchecked, 5.3 ms checked; 1,000 instances 1.3 ms and 3.0 ms; 200,000 triangles and 100,000 instances within
the run-to-run noise (257 vs 202 ms, 277 vs 315 ms).
"""

from __future__ import annotations

import contextlib
import logging
import re
from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

from jaxrt._src.kinds import registry
from jaxrt._src.kinds.registry import BOUNDING_BOX, CURVE, TRIANGLE


class BuildCheckError(ValueError):
    """A build's input breaks a rule that its constructor could not check on traced arrays.

    Raised by builds with ``checks=True``; around jitted code, catch it with :func:`build_check_errors`.
    """


_CARRIED = re.compile(r"BuildCheckError: (.*)")


def build_check_message(error: BaseException) -> str | None:
    """The :class:`BuildCheckError` message that a ``jax.errors.JaxRuntimeError`` carries (``None`` if none)."""
    found = _CARRIED.findall(str(error))
    return found[-1].strip() if found else None


@contextlib.contextmanager
def build_check_errors() -> Iterator[None]:
    """Raise a checked build's failure in jitted code as :class:`BuildCheckError`, with its one-line message.

    Inside ``jax.jit`` the error of a ``checks=True`` build reaches Python as a ``jax.errors.JaxRuntimeError``
    carrying the callback's traceback, which ``except rt.BuildCheckError`` does not catch. Within this block
    such an error is raised again as a :class:`BuildCheckError` (from ``None``); other errors pass unchanged.
    Also usable as a decorator (``@rt.build_check_errors()``). The error shows when the computation runs:
    wait for the result inside the block (``jax.block_until_ready``), since on an accelerator a call may
    return before its computation ends.

    Examples:
      >>> import jax, jax.numpy as jnp, jaxrt as rt
      >>> build = jax.jit(lambda v: rt.build_primitive_structure(rt.TriangleGeometry(v), checks=True))
      >>> try:
      ...     with rt.build_check_errors():
      ...         _ = jax.block_until_ready(build(jnp.array([[0.0, 0, 0], [1, 0, 0], [0, jnp.nan, 0]])))
      ... except rt.BuildCheckError as error:
      ...     print(error)
      build_primitive_structure: geometries[0] (TriangleGeometry) vertices[2] = [ 0., nan, 0.] is not finite
    """
    try:
        yield
    except jax.errors.JaxRuntimeError as error:
        message = build_check_message(error)
        if message is None:
            raise
        raise BuildCheckError(message) from None


class _QuietBuildChecks(logging.Filter):
    """Drops JAX's second report of a failed check ("jax.io_callback failed" and a traceback on stderr): the
    error itself reaches the caller."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, BuildCheckError)


logging.getLogger("jax._src.callback").addFilter(_QuietBuildChecks())


class _Rule(NamedTuple):
    message: str  # with ``{index}`` and ``{value}``
    bad: jax.Array  # (N,) bool
    value: jax.Array  # (N, ...) the rows shown in the message


def _concrete(*arrays: Any) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _format(value: np.ndarray) -> str:
    """``value`` on one line (a transform's rows too), so that the message stays one line."""
    text = np.array2string(np.asarray(value), precision=6, separator=", ", max_line_width=10**6)
    return " ".join(text.split())


def enforce(rules: Sequence[_Rule]) -> None:
    """Raise :class:`BuildCheckError` for the first rule with a bad row (on the host when the inputs are traced)."""
    rules = [r for r in rules if r.bad.shape[0] > 0]
    if not rules:
        return
    if _concrete(*(a for r in rules for a in (r.bad, r.value))):
        _raise_first([(np.any(np.asarray(r.bad)), np.argmax(np.asarray(r.bad))) for r in rules], rules, None)
        return
    found = [(jnp.any(r.bad), jnp.argmax(r.bad)) for r in rules]
    values = [r.value[i] for r, (_, i) in zip(rules, found, strict=True)]
    messages = [r.message for r in rules]

    def host(found, values):
        _raise_first(found, messages, values)

    io_callback(host, None, found, values, ordered=False)


def _raise_first(found, rules_or_messages, values) -> None:
    for k, (any_bad, index) in enumerate(found):
        any_bad, index = np.asarray(any_bad), np.asarray(index)
        if not np.any(any_bad):
            continue
        rule = rules_or_messages[k]
        message = rule if isinstance(rule, str) else rule.message
        if values is None:
            value = np.asarray(rule.value)[int(index)]
        else:
            value = np.asarray(values[k])
        if any_bad.ndim:  # under vmap: the first batch element with a bad row
            b = int(np.argmax(any_bad.reshape(-1)))
            index = index.reshape(-1)[b]
            value = value.reshape(-1, *value.shape[any_bad.ndim :])[b]
            message = f"(batch element {b}) {message}"
        raise BuildCheckError(message.format(index=int(index), value=_format(value)))


# --- the rules ------------------------------------------------------------------------------------------------


def _not_finite(array: jax.Array) -> jax.Array:
    return ~jnp.all(jnp.isfinite(array.reshape(array.shape[0], -1)), axis=1)


def geometry_rules(geometries: Sequence[Any], owner: str) -> list[_Rule]:
    """The rules of triangle, curve and bounding-box geometries (by the attributes each kind has), and those each
    other kind declares (:attr:`~jaxrt._src.kinds.kind.Kind.checks`: spheres)."""
    rules = []
    for g, geometry in enumerate(geometries):
        name = f"{owner}: geometries[{g}] ({type(geometry).__name__})"
        if TRIANGLE.holds(geometry):
            vertices, indices = geometry.vertices, geometry.indices
            count = vertices.shape[0]
            rules.append(_Rule(name + " vertices[{index}] = {value} is not finite", _not_finite(vertices), vertices))
            out = jnp.any((indices < 0) | (indices >= count), axis=1)
            rules.append(
                _Rule(name + f" indices[{{index}}] = {{value}} is out of range for {count} vertices", out, indices)
            )
        elif CURVE.holds(geometry):
            points, radii, first = geometry.control_points, geometry.radii, geometry.indices
            count = points.shape[0]
            rules.append(_Rule(name + " control_points[{index}] = {value} is not finite", _not_finite(points), points))
            bad_radius = ~jnp.isfinite(radii) | (radii < 0)
            rules.append(_Rule(name + " radii[{index}] = {value} is negative or not finite", bad_radius, radii))
            last = geometry.control_point_count - 1
            out = (first < 0) | (first + last >= count)
            rules.append(
                _Rule(
                    name + f" indices[{{index}}] = {{value}}: the segment's {last + 1} control points run past the "
                    f"{count} control points",
                    out,
                    first,
                )
            )
        elif BOUNDING_BOX.holds(geometry):
            box = jnp.stack([geometry.lower, geometry.upper], axis=1)
            rules.append(_Rule(name + " box {index} (lower, upper) = {value} is not finite", _not_finite(box), box))
            inverted = jnp.any(geometry.lower > geometry.upper, axis=-1)
            rules.append(_Rule(name + " box {index} (lower, upper) = {value} has lower > upper", inverted, box))
        else:  # a kind that declares its own rules
            kind = next((k for k in registry.KINDS if k.holds(geometry)), None)
            if kind is not None and kind.checks is not None:
                rules.extend(_Rule(name + " " + message, bad, value) for message, bad, value in kind.checks(geometry))
    return rules


def check_geometries(geometries: Sequence[Any], owner: str = "build_primitive_structure") -> None:
    """Raise :class:`BuildCheckError` for non-finite coordinates, bad radii, inverted boxes or indices out of range."""
    enforce(geometry_rules(geometries, owner))


def check_instances(
    instances: Any, structure_count: int, count: Any, singular_tolerance: float, owner: str = "build_instance_structure"
) -> None:
    """Raise :class:`BuildCheckError` for non-finite or singular transforms and structure indices out of range.

    Only instances below ``count`` (``None``: all) are checked: the others do not exist.
    """
    transform, index = instances.transform, instances.structure_index
    n = transform.shape[-3]
    exists = jnp.arange(n) < (n if count is None else count)
    linear = transform[..., :3]
    det = jnp.linalg.det(linear)
    scale = jnp.prod(jnp.sqrt(jnp.sum(linear * linear, axis=-1)), axis=-1)
    relative = jnp.where(scale > 0, jnp.abs(det) / jnp.where(scale > 0, scale, 1.0), 0.0)
    not_finite = _not_finite(transform) & exists
    rules = [
        _Rule(f"{owner}: instances.transform[{{index}}] = {{value}} is not finite", not_finite, transform),
        _Rule(
            f"{owner}: instances.transform[{{index}}] = {{value}} is singular (relative determinant below "
            f"{singular_tolerance}); an instance transform must be invertible",
            exists & ~not_finite & (relative < singular_tolerance),
            transform,
        ),
        _Rule(
            f"{owner}: instances.structure_index[{{index}}] = {{value}} is out of range for {structure_count} structures",
            exists & ((index < 0) | (index >= structure_count)),
            index,
        ),
    ]
    enforce(rules)
