"""``python -m jaxrt.bench``: jaxrt's speed against its error, with Embree as the peer on the same rays.

Run ``python -m jaxrt.bench --help`` for the flags. The pieces are importable for other benches:

- :mod:`jaxrt.bench.scenes`: ``noisy_sphere``, ``random_soup``, ``shared_mesh``, ``load_scene`` (NumPy meshes).
- :mod:`jaxrt.bench.rays`: ``primary_rays``, ``diffuse_rays``, ``shadow_rays`` (a ``RayBatch`` of NumPy arrays).
- :mod:`jaxrt.bench.reference`: float64 reference hits and ``error_stats`` against them.
- :mod:`jaxrt.bench.peers`: Embree through embreex.
- :mod:`jaxrt.bench.tracer`, :mod:`jaxrt.bench.timing`, :mod:`jaxrt.bench.suite`, :mod:`jaxrt.bench.report`,
  :mod:`jaxrt.bench.cli`: jaxrt as a subject, timing, the per-scene measurements, output, the command line.
"""

from jaxrt.bench.cli import main

__all__ = ["main"]
