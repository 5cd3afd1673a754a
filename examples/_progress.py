"""Progress bars for the examples' long loops: tqdm on a terminal, nothing when quiet or piped."""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import TypeVar

T = TypeVar("T")


def progress(iterable: Iterable[T], *, quiet: bool = False, **options) -> Iterable[T]:
    """``iterable`` wrapped in a tqdm bar on stderr, unless ``quiet``, stderr is not a terminal, or tqdm is not
    installed (``pip install 'jaxrt[demo]'``)."""
    if quiet or not sys.stderr.isatty():
        return iterable
    try:
        from tqdm import tqdm
    except ImportError:
        return iterable
    return tqdm(iterable, leave=False, dynamic_ncols=True, **options)
