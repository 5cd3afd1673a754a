"""Doctest collection of this package: the Triton kernel module imports Triton, which CPU-only installs lack."""

import importlib.util

collect_ignore = [] if importlib.util.find_spec("triton") else ["triton_kernel.py"]
