"""Opt-in input checks of builds that also work on traced arrays (``checks=True``).

Geometry and :class:`~jaxrt.Instances` constructors validate concrete arrays on the host. Inside ``jax.jit``
their arrays are tracers, and a NaN vertex, an index out of range or a singular transform used to make rays
miss without a word. With ``checks=True`` a build computes, on the device, a flag and the first offending
element of each rule, and hands them to one host callback (``jax.experimental.io_callback``) that raises
:class:`BuildCheckError` naming the function, the argument, the element and its value. Inside ``jit`` the
error reaches the caller as a ``jax.errors.JaxRuntimeError`` whose message contains the
``BuildCheckError: ...`` line (when the computation runs, not when it is traced); with concrete arrays it is
raised directly.

Cost: one reduction per rule over the input arrays and one device-to-host synchronisation per build; off by
default. Measured on a shared 2-core CPU (jax 0.10.2, jitted builds, steady state): 10,000 triangles 4.2 ms
unchecked, 5.3 ms checked; 1,000 instances 1.3 ms and 3.0 ms; 200,000 triangles and 100,000 instances within
the run-to-run noise (257 vs 202 ms, 277 vs 315 ms).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

from jaxrt._src.kinds.registry import BOUNDING_BOX, CURVE, TRIANGLE


class BuildCheckError(ValueError):
    """A build's input breaks a rule that its constructor could not check on traced arrays."""


class _Rule(NamedTuple):
    message: str  # with ``{index}`` and ``{value}``
    bad: jax.Array  # (N,) bool
    value: jax.Array  # (N, ...) the rows shown in the message


def _concrete(*arrays: Any) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _format(value: np.ndarray) -> str:
    return np.array2string(np.asarray(value), precision=6, separator=", ")


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
    """The rules of triangle, curve and bounding-box geometries (by the attributes each kind has)."""
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
