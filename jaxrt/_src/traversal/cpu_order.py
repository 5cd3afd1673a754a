"""The order in which the CPU traversal traces a batch of rays: along a Morton curve of origin and direction.

Rays that start near each other and point the same way visit mostly the same nodes. Traced one after the other,
they find those nodes in the cache and take the same branches, which the branch predictor learns; a batch in
random order (diffuse bounces from random surface points) pays a cache miss and a mispredicted branch on most
visits. :func:`ray_order` sorts the rays by a 24-bit key, four bits of each origin coordinate (in the scene's
bounds) and of each direction coordinate, interleaved (a six-dimensional Morton code), with two passes of a
radix sort; :func:`coherent` tells a batch that is in such an order already (a camera's rays, pixel after
pixel), which is traced as given. Each ray is still traced on its own with the same operations: the order changes
the speed, never a result.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["coherent", "permuted", "ray_order", "unpermuted"]

#: Bits of the sort key per coordinate (six coordinates), and bits of one radix pass (two passes).
BITS = 4
DIGIT = 12
#: Consecutive pairs of rays :func:`coherent` samples, and the fraction of them in one key cell that makes a
#: batch coherent.
SAMPLES = 1024
SAME_CELL = 0.5


@numba.njit(cache=True)
def _spread(q):
    """``q``, a float in ``[0, 16)``, as four bits moved to bits 0, 6, 12 and 18."""
    x = np.uint64(np.int64(q)) & np.uint64(15)
    return (x | (x << np.uint64(5)) | (x << np.uint64(10)) | (x << np.uint64(15))) & np.uint64(0x41041)


@numba.njit(cache=True)
def _cell(x, low, scale, top):
    """``(x - low) * scale`` clamped to ``[0, top]`` (NaN to 0)."""
    return min(max(0.0, (x - low) * scale), top)


@numba.njit(cache=True)
def _frame(lower, upper):
    """The key's constants for the box ``lower, upper``: its lower corner, the scale of each axis and the top
    cell coordinate."""
    top = float(1 << BITS) - 1e-3
    l0, l1, l2 = float(lower[0]), float(lower[1]), float(lower[2])
    e0, e1, e2 = float(upper[0]) - l0, float(upper[1]) - l1, float(upper[2]) - l2
    s0 = top / e0 if e0 > 0 else 0.0
    s1 = top / e1 if e1 > 0 else 0.0
    s2 = top / e2 if e2 > 0 else 0.0
    return l0, l1, l2, s0, s1, s2, top


@numba.njit(cache=True)
def _key(origin, direction, i, frame):
    """Ray ``i``'s 24-bit Morton key: its origin's cell in the frame's box (:func:`_frame`) and the cell of its
    direction scaled to ``[-1, 1]`` by its largest component."""
    l0, l1, l2, s0, s1, s2, top = frame
    d0, d1, d2 = float(direction[i, 0]), float(direction[i, 1]), float(direction[i, 2])
    m = max(abs(d0), abs(d1), abs(d2))
    h = 0.5 * top / m if m > 0 else 0.0
    k = _spread(_cell(float(origin[i, 0]), l0, s0, top)) << np.uint64(5)
    k |= _spread(_cell(float(origin[i, 1]), l1, s1, top)) << np.uint64(4)
    k |= _spread(_cell(float(origin[i, 2]), l2, s2, top)) << np.uint64(3)
    k |= _spread(_cell(d0, -m, h, top)) << np.uint64(2)
    k |= _spread(_cell(d1, -m, h, top)) << np.uint64(1)
    k |= _spread(_cell(d2, -m, h, top))
    return np.uint32(k)


@numba.njit(nogil=True, cache=True)
def coherent(origin, direction, lower, upper):
    """Whether the rays are in a coherent order already: at least :data:`SAME_CELL` of up to :data:`SAMPLES`
    evenly spaced pairs of consecutive rays share their key cell (:func:`_key`; the box ``lower, upper``)."""
    n = origin.shape[0]
    pairs = min(SAMPLES, n - 1)
    if pairs < 1:
        return True
    frame = _frame(lower, upper)
    same = 0
    for p in range(pairs):
        i = p * (n - 1) // pairs
        same += _key(origin, direction, i, frame) == _key(origin, direction, i + 1, frame)
    return same >= SAME_CELL * pairs


@numba.njit(nogil=True, cache=True)
def ray_order(origin, direction, lower, upper):
    """The indices of the rays ``origin, direction`` (``(n, 3)``) sorted stably by their Morton keys
    (:func:`_key`, the origins' cells taken in the box ``lower, upper``): int32, a permutation of ``0..n-1``."""
    n = origin.shape[0]
    frame = _frame(lower, upper)
    keys = np.empty(n, np.uint32)
    for i in range(n):
        keys[i] = _key(origin, direction, i, frame)
    mask = np.uint32((1 << DIGIT) - 1)
    low = np.zeros(1 << DIGIT, np.int64)
    high = np.zeros(1 << DIGIT, np.int64)
    for i in range(n):
        low[keys[i] & mask] += 1
        high[keys[i] >> np.uint32(DIGIT)] += 1
    first_low = 0
    first_high = 0
    for digit in range(1 << DIGIT):  # counts to the first position of each digit
        count_low, count_high = low[digit], high[digit]
        low[digit], high[digit] = first_low, first_high
        first_low += count_low
        first_high += count_high
    by_low = np.empty(n, np.int32)
    for i in range(n):
        digit = keys[i] & mask
        by_low[low[digit]] = i
        low[digit] += 1
    order = np.empty(n, np.int32)
    for i in by_low:
        digit = keys[i] >> np.uint32(DIGIT)
        order[high[digit]] = i
        high[digit] += 1
    return order


@numba.njit(nogil=True, cache=True)
def _take_rows(a, order, out):
    """``out[j] = a[order[j]]`` for rows of words."""
    for j in range(order.shape[0]):
        i = order[j]
        for c in range(a.shape[1]):
            out[j, c] = a[i, c]


@numba.njit(nogil=True, cache=True)
def _put_rows(a, order, out):
    """``out[order[j]] = a[j]`` for rows of words."""
    for j in range(order.shape[0]):
        i = order[j]
        for c in range(a.shape[1]):
            out[i, c] = a[j, c]


def _words(a: np.ndarray) -> np.ndarray:
    """A contiguous array's rows (its first axis) as rows of 4-byte words where they divide, else of bytes."""
    rows = a.reshape(a.shape[0], -1)
    return rows.view(np.uint32) if rows.shape[1] * a.itemsize % 4 == 0 else rows.view(np.uint8)


def permuted(a: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``a[order]`` (along the first axis) for a contiguous array, copied by compiled loops."""
    out = np.empty_like(a)
    _take_rows(_words(a), order, _words(out))
    return out


def unpermuted(a: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The array ``b`` with ``b[order] = a`` (along the first axis) for a contiguous array."""
    out = np.empty_like(a)
    _put_rows(_words(a), order, _words(out))
    return out
