#!/usr/bin/env bash
# Build the documentation site with warnings as errors (mkdocs build --strict) into site/.
#
#   bash scripts/docs.sh [VENV]    # VENV: the virtual environment to use (default .venv, created on first use)
#
# Installs the package with its [docs] extra (mkdocs-material, mkdocstrings) in setuptools' "compat" editable
# mode, as scripts/test.sh does, then builds. Preview with `VENV/bin/mkdocs serve`.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
[ -x "$VENV/bin/python" ] || "${PYTHON:-python3}" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --config-settings editable_mode=compat -e ".[docs]"
start=$SECONDS
NO_MKDOCS_2_WARNING=1 "$VENV/bin/python" -m mkdocs build --strict --clean --site-dir site
echo "scripts/docs.sh: site/ built in $((SECONDS - start)) s"
