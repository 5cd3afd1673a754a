"""Doctest collection of this package: the Triton kernel modules (``triton_*.py``) import Triton, which CPU-only
installs lack."""

import importlib.util

collect_ignore_glob = [] if importlib.util.find_spec("triton") else ["triton_*.py"]
