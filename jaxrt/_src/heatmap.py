"""Traversal heatmaps: per-ray traversal counters rendered as an RGB image (an acceleration-structure viewer).

Xcode's acceleration-structure viewer has a "traversal" mode that colours each pixel by the work its ray did.
The ``stats`` tag (``rt.tags.stats``) returns that work per ray (``nodes_visited``, ``primitives_tested``);
here it becomes a picture: values are scaled to ``[0, 1]`` and mapped through a colormap. The colormap is
computed here (no matplotlib): Google's Turbo, from the polynomial approximation its authors published.

References:
  Anton Mikhailov, "Turbo, An Improved Rainbow Colormap for Visualization", Google AI Blog, 2019 (the
  polynomial approximation by Ruofei Du, Apache-2.0).
"""

from __future__ import annotations

import struct
import zlib
from typing import Any

import numpy as np

from jaxrt import tags
from jaxrt._src.intersector import Intersector

__all__ = ["COLORMAPS", "colormap", "heatmap", "traversal_heatmap", "write_png", "colorbar"]

# Turbo as two polynomials per channel: c(x) = v4 . (1, x, x^2, x^3) + v2 . (x^4, x^5).
_TURBO4 = np.array(
    [
        [0.13572138, 4.61539260, -42.66032258, 132.13108234],
        [0.09140261, 2.19418839, 4.84296658, -14.18503333],
        [0.10667330, 12.64194608, -60.58204836, 110.36276771],
    ]
)
_TURBO2 = np.array([[-152.94239396, 59.28637943], [4.27729857, 2.82956604], [-89.90310912, 27.34824973]])


def _turbo(x: np.ndarray) -> np.ndarray:
    powers = np.stack([np.ones_like(x), x, x**2, x**3, x**4, x**5], axis=-1)
    return np.clip(powers @ np.concatenate([_TURBO4, _TURBO2], axis=1).T, 0.0, 1.0)


def _gray(x: np.ndarray) -> np.ndarray:
    return np.repeat(x[..., None], 3, axis=-1)


#: Colormaps by name: ``fn(x in [0, 1]) -> RGB in [0, 1]``.
COLORMAPS = {"turbo": _turbo, "gray": _gray}


def colormap(values: Any, *, vmin: float = 0.0, vmax: float | None = None, name: str = "turbo") -> np.ndarray:
    """Map values to colours: ``(...,)`` numbers to ``(..., 3)`` uint8 RGB.

    Args:
      values: any array of numbers; NaN maps to black.
      vmin, vmax: the values mapped to the two ends of the colormap (clipped outside); ``vmax=None`` takes the
        largest finite value.
      name: a key of :data:`COLORMAPS` (``"turbo"``: dark blue for little work to dark red for much).

    Returns:
      A ``uint8`` array of shape ``values.shape + (3,)``.

    Raises:
      ValueError: an unknown colormap name, or ``vmax <= vmin``.

    Examples:
      >>> from jaxrt import debug
      >>> debug.colormap([0, 10], name="gray").tolist()
      [[0, 0, 0], [255, 255, 255]]
    """
    if name not in COLORMAPS:
        raise ValueError(f"colormap: name must be one of {sorted(COLORMAPS)}, got {name!r}")
    values = np.asarray(values, np.float64)
    finite = values[np.isfinite(values)]
    if vmax is None:
        vmax = float(finite.max()) if finite.size else vmin + 1.0
        vmax = vmax if vmax > vmin else vmin + 1.0
    if not vmax > vmin:
        raise ValueError(f"colormap: vmax must exceed vmin, got vmin={vmin}, vmax={vmax}")
    x = np.clip((values - vmin) / (vmax - vmin), 0.0, 1.0)
    rgb = COLORMAPS[name](np.nan_to_num(x))
    rgb = np.where(np.isnan(values)[..., None], 0.0, rgb)
    return np.round(rgb * 255.0).astype(np.uint8)


def heatmap(counts: Any, *, vmax: float | None = None, name: str = "turbo") -> np.ndarray:
    """An image of per-pixel counts (``(H, W)``) as ``(H, W, 3)`` uint8 RGB, 0 at the cold end.

    Args:
      counts: ``(H, W)`` numbers, e.g. ``result.nodes_visited`` of rays made per pixel.
      vmax: the count shown at the hot end (``None``: the image's maximum). Fix it to compare images.
      name: a key of :data:`COLORMAPS`.

    Returns:
      ``(H, W, 3)`` uint8.

    Raises:
      ValueError: ``counts`` is not two-dimensional (or see :func:`colormap`).

    Examples:
      >>> import numpy as np
      >>> from jaxrt import debug
      >>> debug.heatmap(np.arange(6).reshape(2, 3)).shape
      (2, 3, 3)
    """
    counts = np.asarray(counts)
    if counts.ndim != 2:
        raise ValueError(f"heatmap: counts must have shape (H, W), got {counts.shape}")
    return colormap(counts, vmin=0.0, vmax=vmax, name=name)


_FIELDS = ("nodes_visited", "primitives_tested")


def traversal_heatmap(
    structure: Any,
    rays: Any,
    *,
    field: str = "nodes_visited",
    intersector: Any = None,
    vmax: float | None = None,
    name: str = "turbo",
) -> tuple[np.ndarray, np.ndarray]:
    """Trace ``rays`` (one per pixel) and render the traversal work of each as a heatmap.

    Args:
      structure: any acceleration structure.
      rays: an :class:`~jaxrt.Ray` of batch shape ``(H, W)`` (e.g. from ``rt.shading.pinhole_rays``).
      field: ``"nodes_visited"`` (box tests: the viewer's traversal mode) or ``"primitives_tested"``.
      intersector: an :class:`~jaxrt.Intersector` carrying ``rt.tags.stats``; ``None`` makes one with
        ``stats`` (and ``instancing`` with enough levels for an instance structure).
      vmax, name: as for :func:`heatmap`.

    Returns:
      ``(image, counts)``: ``(H, W, 3)`` uint8 RGB and the ``(H, W)`` counts it shows.

    Raises:
      ValueError: an unknown ``field``, an intersector without the ``stats`` tag, or rays that are not
        ``(H, W)``.
    """
    if field not in _FIELDS:
        raise ValueError(f"traversal_heatmap: field must be one of {_FIELDS}, got {field!r}")
    if intersector is None:
        wanted = [tags.stats]
        if structure.levels:
            wanted += [tags.instancing, tags.max_levels(structure.levels)]
        intersector = Intersector(*wanted)
    elif tags.stats not in intersector.tags:
        raise ValueError(f"traversal_heatmap: intersector needs the rt.tags.stats tag, it has {intersector.tags}")
    counts = np.asarray(getattr(intersector.intersect(rays, structure), field))
    if counts.ndim != 2:
        raise ValueError(f"traversal_heatmap: rays must have batch shape (H, W), got {counts.shape}")
    return heatmap(counts, vmax=vmax, name=name), counts


def colorbar(width: int = 256, height: int = 16, *, name: str = "turbo") -> np.ndarray:
    """A horizontal ``(height, width, 3)`` uint8 strip of the colormap, cold on the left (for a legend)."""
    return np.repeat(colormap(np.linspace(0.0, 1.0, width), vmax=1.0, name=name)[None], height, axis=0)


def write_png(path: Any, image: Any) -> None:
    """Write an ``(H, W, 3)`` uint8 RGB image as an 8-bit PNG (zlib only; no imaging library).

    Raises:
      ValueError: ``image`` is not ``(H, W, 3)`` uint8.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"write_png: image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    height, width = image.shape[:2]
    rows = np.concatenate([np.zeros((height, 1), np.uint8), image.reshape(height, width * 3)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows.tobytes(), 9))
    with open(path, "wb") as file:
        file.write(png + chunk(b"IEND", b""))
