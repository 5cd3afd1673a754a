"""Time the LBVH build and its stages on the default device (median of warm calls).

Usage: ``python scripts/build_profile.py [SIZE ...]`` (triangles per scene; default 2**20, 4M, 10M). Each stage
is jitted and timed on its own (so the stages add up to more than the build); the radix tree and the node
boxes are timed as loops and unrolled (the build unrolls them on accelerators).
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxrt as rt
from jaxrt._src import structures as st
from jaxrt._src.bvh.boxes import child_boxes, range_boxes
from jaxrt._src.bvh.morton import morton_codes
from jaxrt._src.bvh.radix_tree import build_radix_tree
from jaxrt.bench.scenes import noisy_sphere, random_soup


def median_ms(fn, *args, repeats=7):
    jax.block_until_ready(fn(*args))
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def report(name, scene):
    g = rt.TriangleGeometry(jnp.asarray(scene.vertices), jnp.asarray(scene.indices))
    n = g.primitive_count
    cap = st.capacity_bucket(n)
    build = jax.jit(lambda g: rt.build_primitive_structure(g))
    full = median_ms(build, g)
    prims = jax.jit(lambda g: st._leaf_primitives((g,), cap))
    t_prims = median_ms(prims, g)
    tri, gid, pid, lo, hi, valid, _, _ = prims(g)
    codes_fn = jax.jit(lambda lo, hi, v: morton_codes(lo, hi, v))
    t_codes = median_ms(codes_fn, lo, hi, valid)
    codes = codes_fn(lo, hi, valid)[:n]
    sort = jax.jit(lambda c: lax.sort((c, jnp.arange(c.shape[0], dtype=jnp.int32)), num_keys=1, is_stable=True))
    t_sort = median_ms(sort, codes)
    sc, order = sort(codes)
    radix = jax.jit(lambda c: build_radix_tree(c, unroll=False))
    t_radix = median_ms(radix, sc)
    t_radix_u = median_ms(jax.jit(lambda c: build_radix_tree(c, unroll=True)), sc)
    ch, first, last = radix(sc)
    llo, lhi = lo[order], hi[order]
    boxes = jax.jit(lambda f, la, a, b: range_boxes(a, b, f, la, unroll=False))
    t_range = median_ms(boxes, first, last, llo, lhi)
    t_range_u = median_ms(jax.jit(lambda f, la, a, b: range_boxes(a, b, f, la, unroll=True)), first, last, llo, lhi)
    nlo, nhi = boxes(first, last, llo, lhi)
    cb = jax.jit(child_boxes)
    t_child = median_ms(cb, ch, nlo, nhi, llo, lhi)
    gather = jax.jit(lambda t, a, b, o: (t[o], a[o], b[o]))
    t_gather = median_ms(gather, tri[:n], gid[:n], pid[:n], order)
    print(
        f"{name:8s} n={n:>10,} cap={cap:>10,} build {full:7.2f} ms ({n / full / 1e3:6.0f} Mprims/s) | prims {t_prims:.2f} codes {t_codes:.2f} "
        f"sort {t_sort:.2f} radix {t_radix:.2f} (unrolled {t_radix_u:.2f}) range_boxes {t_range:.2f} (unrolled {t_range_u:.2f}) child_boxes {t_child:.2f} gathers {t_gather:.2f}",
        flush=True,
    )


print(jax.devices())
for size in [int(a) for a in sys.argv[1:]] or [1 << 20, 4_000_000, 10_000_000]:
    report("soup", random_soup(size))
    report("sphere", noisy_sphere(size))
