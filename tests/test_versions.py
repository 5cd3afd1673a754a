"""The tested jax range, its warning, the workaround of jaxlib 0.11's CPU fusion defect, and the import of a
clone in a folder named jaxrt."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import jax
import pytest

from jaxrt._src import versions

ROOT = Path(__file__).resolve().parents[1]


def test_pyproject_states_the_range_the_package_checks():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    jax_requirement = [d for d in project["dependencies"] if re.match(r"jax\b", d)]
    assert jax_requirement == [versions.tested_range()]


def test_the_installed_jax_is_in_the_tested_range():
    assert versions.check_jax_version(jax.__version__) is None, versions.check_jax_version(jax.__version__)


@pytest.mark.parametrize("version", ["0.10.2", "0.11.2", "0.12.0.1", "0.12.0"])
def test_versions_inside_the_range_pass(version):
    assert versions.check_jax_version(version) is None


@pytest.mark.parametrize("version", ["0.4.35", "0.10.1", "0.12.1", "0.13.0", "1.0.0", "0.13.0.dev20270101"])
def test_versions_outside_the_range_get_a_message_naming_it(version):
    message = versions.check_jax_version(version)
    assert message is not None and f"jax {version}" in message and versions.tested_range() in message


def test_an_untested_jax_warns_at_import(monkeypatch):
    monkeypatch.setattr(jax, "__version__", "0.13.1")
    with pytest.warns(versions.JaxVersionWarning, match=re.escape("jaxrt is tested with jax>=0.10.2,<0.12.1")):
        versions.check_at_import()


def test_parse():
    assert versions.parse("0.12.0.1") == (0, 12, 0, 1)
    assert versions.parse("0.13.0rc2") == (0, 13, 0)
    assert versions.parse("0.10.2.dev20260101") == (0, 10, 2)


def test_the_ynn_fusion_is_turned_off_on_jaxlib_0_11_only():
    flag = "--xla_cpu_experimental_ynn_fusion_type="
    environ = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert versions.work_around_ynn_defect("0.11.2", environ) is None
    assert environ["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {flag}"
    for version in ("0.10.2", "0.12.0.1"):  # XLA rejects flags it does not know: leave other versions alone
        environ = {}
        assert versions.work_around_ynn_defect(version, environ) is None and environ == {}
    chosen = {"XLA_FLAGS": f"{flag}+individual_dot"}  # the user's own choice stays
    assert versions.work_around_ynn_defect("0.11.0", dict(chosen)) is None
    late = {}
    message = versions.work_around_ynn_defect("0.11.2", late, initialized=True)
    assert late == {} and "import jaxrt first" in message


def test_a_clone_named_jaxrt_imports_the_package_from_the_folder_above(tmp_path):
    """With the repository in a folder named ``jaxrt``, a script in the folder above still gets the package.

    A namespace package made of the clone would shadow an import hook (setuptools' default editable mode);
    ``scripts/test.sh`` installs in "compat" mode (a path entry) so that the package wins.
    """
    (tmp_path / "jaxrt").symlink_to(ROOT, target_is_directory=True)
    script = "import jaxrt; print(jaxrt.io.__name__, jaxrt.Intersector.__name__)"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ""}
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert run.returncode == 0 and "jaxrt.io Intersector" in run.stdout, (
        "a script next to a clone named jaxrt imported the clone as a namespace package; install with "
        "`pip install -e . --config-settings editable_mode=compat` (as scripts/test.sh does):\n" + run.stderr[-2000:]
    )
