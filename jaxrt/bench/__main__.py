"""``python -m jaxrt.bench``: see :mod:`jaxrt.bench`."""

import sys

from jaxrt.bench.cli import main

sys.exit(main())
