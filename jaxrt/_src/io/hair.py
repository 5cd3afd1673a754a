"""Hair strands from files: AMD TressFX ``.tfx`` (versions 3 and 4) and Cem Yuksel's ``.hair`` format.

A file holds strands: polylines of points (and, for ``.hair``, a thickness per point). :func:`load_hair`
reads one and turns its strands into curve segments ready for :class:`jaxrt.CurveGeometry`
(:func:`strands_to_curves`): linear segments through the points, or Catmull-Rom / B-spline segments with a
phantom point added at each end of every strand (the reflection of the second point through the first), so
that the curve starts and ends at the strand's end points and spans every point-to-point interval.

Formats (little-endian):

* TressFX 3 (``version == 3.0``), 296-byte header: ``float version; u32 numStrands, pointsPerStrand,
  numFollowHairsPerGuide, bothEndsImmovable; u32 reserved[31]; u32 verticesOffset, thicknessOffset,
  strandUVOffset, vertexColorOffset, guideStrandOffset, vertexUVOffset; u32 reserved[32]``; positions
  ``float32[numStrands][pointsPerStrand][3]`` at ``verticesOffset``.
* TressFX 4 (``version == 4.0``), 160-byte header: ``float version; u32 numStrands, pointsPerStrand,
  offsetVertexPosition, offsetStrandUV, offsetVertexUV, offsetStrandThickness, offsetVertexColor;
  u32 reserved[32]``; positions ``float32[numStrands][pointsPerStrand][4]`` (``w`` = inverse mass, ignored).
  TressFX stores no radius: pass ``width``.
* ``.hair`` (Cem Yuksel), 128-byte header: ``char[4] "HAIR"; u32 hair_count, point_count, arrays,
  default_segments; float default_thickness, default_transparency, default_color[3]; char info[88]``, then,
  when their bit of ``arrays`` is set, ``u16 segments[hair_count]`` (bit 0), ``float32 points[point_count][3]``
  (bit 1), ``float32 thickness[point_count]`` (bit 2), ``float32 transparency[point_count]`` (bit 3) and
  ``float32 color[point_count][3]`` (bit 4). A strand of ``s`` segments has ``s + 1`` points; thickness is
  the strand's width (diameter), so the radius is half of it.

References:
  AMD GPUOpen, TressFX 3.1 and 4.1 (``TressFXAsset`` loaders, MIT licence).
  Yuksel, "HAIR file format", cemyuksel.com/research/hairmodels (the format of the Yuksel et al. hair models).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from jaxrt._src.curves import CurveGeometry

__all__ = [
    "HairStrands",
    "HairCurves",
    "read_tfx",
    "read_hair",
    "write_hair",
    "strands_to_curves",
    "load_hair",
]

_TFX3_HEADER = 296
_TFX4_HEADER = 160
_HAIR_HEADER = 128
_HAIR_SEGMENTS, _HAIR_POINTS, _HAIR_THICKNESS, _HAIR_TRANSPARENCY, _HAIR_COLORS = 1, 2, 4, 8, 16


class HairStrands(NamedTuple):
    """Strands as stored: concatenated polyline points and the point count of each strand."""

    points: np.ndarray
    """``(P, 3)`` float32 points of all strands, strand after strand."""
    counts: np.ndarray
    """``(N,)`` int64 points per strand (they sum to ``P``)."""
    radii: np.ndarray | None
    """``(P,)`` float32 radius per point, or ``None`` where the file stores none (TressFX)."""


class HairCurves(NamedTuple):
    """Curve segments ready for :class:`jaxrt.CurveGeometry` (``rt.CurveGeometry(*curves[:3], **curves.options)``)."""

    control_points: np.ndarray
    """``(P', 3)`` float32."""
    radii: np.ndarray
    """``(P',)`` float32."""
    indices: np.ndarray
    """``(S,)`` int32 first control point of each segment."""
    basis: str
    control_point_count: int

    @property
    def options(self) -> dict[str, Any]:
        """``basis`` and ``control_point_count`` as keyword arguments."""
        return dict(basis=self.basis, control_point_count=self.control_point_count)

    def geometry(self, **kwargs: Any):
        """A :class:`jaxrt.CurveGeometry` of these segments (``kwargs``: ``curve_type``, ``end_caps``, ...)."""
        return CurveGeometry(self.control_points, self.radii, self.indices, **self.options, **kwargs)


def _read(path: str | os.PathLike[str]) -> bytes:
    return Path(path).read_bytes()


def read_tfx(path: str | os.PathLike[str]) -> HairStrands:
    """Read a TressFX ``.tfx`` file, version 3 (float3 positions) or 4 (float4 positions).

    Args:
      path: the file.

    Returns:
      :class:`HairStrands` with ``radii=None`` (TressFX stores no radius).

    Raises:
      ValueError: an unknown version, or a header whose counts and offsets run past the end of the file.
    """
    data = _read(path)
    name = f"read_tfx({str(path)!r})"
    if len(data) < 12:
        raise ValueError(f"{name}: the file has {len(data)} bytes, too few for a TressFX header")
    version, strands, per_strand = struct.unpack_from("<fII", data, 0)
    if version == 3.0:
        offset = struct.unpack_from("<I", data, 144)[0] if len(data) >= _TFX3_HEADER else 0
        width, header = 3, _TFX3_HEADER
    elif version == 4.0:
        offset = struct.unpack_from("<I", data, 12)[0] if len(data) >= _TFX4_HEADER else 0
        width, header = 4, _TFX4_HEADER
    else:
        raise ValueError(f"{name}: version {version} is not a TressFX version this reader knows (3.0 or 4.0)")
    if len(data) < header:
        raise ValueError(f"{name}: the file has {len(data)} bytes, shorter than the {header}-byte header")
    count = strands * per_strand
    end = offset + 4 * width * count
    if offset < header or end > len(data):
        raise ValueError(
            f"{name}: {strands} strands of {per_strand} points at offset {offset} need bytes up to {end}, "
            f"but the file has {len(data)}"
        )
    positions = np.frombuffer(data, "<f4", count * width, offset).reshape(count, width)[:, :3]
    points = np.ascontiguousarray(positions, np.float32)
    if not np.isfinite(points).all():
        raise ValueError(f"{name}: the positions hold non-finite values")
    return HairStrands(points, np.full(strands, per_strand, np.int64), None)


def read_hair(path: str | os.PathLike[str]) -> HairStrands:
    """Read Cem Yuksel's ``.hair`` format (radii are half the stored thickness).

    Raises:
      ValueError: a wrong signature, no points array, or arrays that run past the end of the file.
    """
    data = _read(path)
    name = f"read_hair({str(path)!r})"
    if len(data) < _HAIR_HEADER or data[:4] != b"HAIR":
        raise ValueError(f"{name}: not a .hair file (it must start with the 128-byte header signed 'HAIR')")
    strands, count, arrays, segments, thickness, _, _, _, _ = struct.unpack_from("<4I5f", data, 4)
    if not arrays & _HAIR_POINTS:
        raise ValueError(f"{name}: the file has no points array (arrays bit field {arrays:#x})")
    offset = _HAIR_HEADER

    def take(dtype: str, n: int) -> np.ndarray:
        nonlocal offset
        size = np.dtype(dtype).itemsize * n
        if offset + size > len(data):
            raise ValueError(f"{name}: the arrays run past the end of the file ({offset + size} > {len(data)} bytes)")
        out = np.frombuffer(data, dtype, n, offset)
        offset += size
        return out

    per_strand = (
        take("<u2", strands).astype(np.int64) if arrays & _HAIR_SEGMENTS else np.full(strands, segments, np.int64)
    )
    counts = per_strand + 1
    if int(counts.sum()) != count:
        raise ValueError(f"{name}: the strands' segments add up to {int(counts.sum())} points, the header says {count}")
    points = take("<f4", 3 * count).reshape(count, 3).astype(np.float32)
    width = take("<f4", count).astype(np.float32) if arrays & _HAIR_THICKNESS else np.full(count, thickness, np.float32)
    if not (np.isfinite(points).all() and np.isfinite(width).all()):
        raise ValueError(f"{name}: the points or thickness hold non-finite values")
    return HairStrands(points, counts, 0.5 * np.abs(width))


def write_hair(
    path: str | os.PathLike[str],
    points: np.ndarray,
    counts: np.ndarray,
    *,
    thickness: np.ndarray | float = 1.0,
    info: str = "",
) -> None:
    """Write strands in Cem Yuksel's ``.hair`` format (a segments array, points and a thickness per point).

    A tiny writer, for test fixtures: no file of this format ships with the project's data.

    Args:
      path: the file to write.
      points: ``(P, 3)`` points of all strands, strand after strand.
      counts: ``(N,)`` points per strand (at least 1 each, at most 65536).
      thickness: width per point ``(P,)`` or one width for all (twice the radius).
      info: up to 88 bytes of text for the header's info field.

    Examples:
      >>> import numpy as np, tempfile, os
      >>> from jaxrt._src.io.hair import read_hair, write_hair
      >>> path = os.path.join(tempfile.mkdtemp(), "two.hair")
      >>> write_hair(path, np.arange(15.0).reshape(5, 3), [2, 3], thickness=0.2)
      >>> read_hair(path).counts.tolist(), float(read_hair(path).radii[0])
      ([2, 3], 0.10000000149011612)
    """
    points = np.asarray(points, np.float32).reshape(-1, 3)
    counts = np.asarray(counts, np.int64).reshape(-1)
    if counts.sum() != len(points) or (counts < 1).any() or (counts > 65536).any():
        raise ValueError(f"write_hair: counts must be in [1, 65536] and sum to the {len(points)} points")
    width = np.broadcast_to(np.asarray(thickness, np.float32), (len(points),))
    arrays = _HAIR_SEGMENTS | _HAIR_POINTS | _HAIR_THICKNESS
    header = b"HAIR" + struct.pack("<4I5f", len(counts), len(points), arrays, 0, 1.0, 0.0, 0.5, 0.5, 0.5)
    header += info.encode()[:88].ljust(88, b"\0")
    body = (counts - 1).astype("<u2").tobytes() + points.astype("<f4").tobytes() + width.astype("<f4").tobytes()
    Path(path).write_bytes(header + body)


def strands_to_curves(strands: HairStrands, *, basis: str = "catmull_rom", width: float | None = None) -> HairCurves:
    """Curve segments along every strand's points.

    Args:
      strands: from :func:`read_tfx` or :func:`read_hair`.
      basis: ``"linear"`` (one segment per point interval), ``"catmull_rom"`` (through every point) or
        ``"bspline"`` (smooth, near the points); the last two add a phantom point at each strand end.
      width: strand width (twice the radius) used when the file has no radii, and required then.

    Returns:
      :class:`HairCurves`; strands of fewer than 2 points are dropped.
    """
    if basis not in ("linear", "catmull_rom", "bspline"):
        raise ValueError(f"strands_to_curves: basis must be 'linear', 'catmull_rom' or 'bspline', got {basis!r}")
    points = np.asarray(strands.points, np.float32)
    if strands.radii is None:
        if width is None:
            raise ValueError("strands_to_curves: the strands have no radii (TressFX); pass width=")
        radii = np.full(len(points), 0.5 * float(width), np.float32)
    else:
        radii = np.asarray(strands.radii, np.float32)
        if width is not None:
            radii = np.full(len(points), 0.5 * float(width), np.float32)
    starts = np.concatenate([[0], np.cumsum(strands.counts)[:-1]]).astype(np.int64)
    keep = strands.counts >= 2
    starts, counts = starts[keep], strands.counts[keep]
    if basis == "linear":
        first = np.concatenate([s + np.arange(c - 1) for s, c in zip(starts, counts, strict=True)])
        return HairCurves(points, radii, first.astype(np.int32), "linear", 2)
    # Phantom end points: P[-1] = 2 P[0] - P[1] and P[n] = 2 P[n-1] - P[n-2], radii copied.
    pieces, radius_pieces, first = [], [], []
    position = 0
    for s, c in zip(starts, counts, strict=True):
        strand = points[s : s + c]
        strand_radii = radii[s : s + c]
        pieces += [2 * strand[:1] - strand[1:2], strand, 2 * strand[-1:] - strand[-2:-1]]
        radius_pieces += [strand_radii[:1], strand_radii, strand_radii[-1:]]
        first.append(position + np.arange(c - 1))
        position += c + 2
    control = np.concatenate(pieces).astype(np.float32)
    return HairCurves(control, np.concatenate(radius_pieces), np.concatenate(first).astype(np.int32), basis, 4)


def load_hair(path: str | os.PathLike[str], *, basis: str = "catmull_rom", width: float | None = None) -> HairCurves:
    """Read a ``.tfx`` or ``.hair`` file (by extension) and return its strands as curve segments.

    Args:
      path: a TressFX ``.tfx`` (version 3 or 4) or a ``.hair`` file.
      basis: see :func:`strands_to_curves`.
      width: strand width; required for TressFX files (they store none), overrides ``.hair`` thickness.

    Returns:
      :class:`HairCurves`; ``rt.CurveGeometry(*curves[:3], **curves.options)`` or ``curves.geometry()``.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".tfx":
        strands = read_tfx(path)
    elif suffix == ".hair":
        strands = read_hair(path)
    else:
        raise ValueError(f"load_hair: cannot tell the format of {str(path)!r}: use a .tfx or .hair file")
    return strands_to_curves(strands, basis=basis, width=width)
