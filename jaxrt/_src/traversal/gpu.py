"""GPU traversal kernel (not available in this version: every intersector falls back to the portable path)."""

from __future__ import annotations

from typing import Any


def unavailable_reason(intersector: Any) -> str | None:
    """Why the GPU kernel cannot run ``intersector`` here, or ``None`` when it can."""
    return "no GPU kernel is built into this version"


def trace(structure, origin, direction, t_min, t_max, enabled, *, any_hit: bool, cull: int):
    """Trace rays with the GPU kernel: returns a ``TraversalResult`` like the portable traversal."""
    raise NotImplementedError("GPU kernel not available")
