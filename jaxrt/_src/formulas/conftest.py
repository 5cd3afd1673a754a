"""Doctest collection of this package: the Triton operations (``ops_triton.py``) import Triton, which CPU-only
installs lack."""

import importlib.util

collect_ignore_glob = [] if importlib.util.find_spec("triton") else ["ops_triton.py"]
