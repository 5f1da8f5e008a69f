"""`pip install .` into a fresh virtual environment: the package is `rig` and nothing else;
the drivers and the simulated rig install inside it (rig.drivers, rig.sim), not as the
generic top-level names `drivers` and `sim_device`."""

from __future__ import annotations

import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _setuptools_ok() -> bool:
    try:
        import setuptools
    except ImportError:
        return False
    return int(setuptools.__version__.split(".")[0]) >= 77


@pytest.mark.skipif(not _setuptools_ok(), reason="building the wheel offline needs setuptools>=77 "
                                                  "(the test extra installs it)")
def test_pip_install_leaves_only_rig_in_site_packages(tmp_path):
    src = tmp_path / "src"  # a copy, so the build leaves nothing in the checkout
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for folder in ("rig", "drivers", "sim_device"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    env = tmp_path / "venv"
    venv.create(env, with_pip=False)
    py = env / "bin" / "python"
    pip = [sys.executable, "-m", "pip"]
    subprocess.run([*pip, "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", str(tmp_path / "dist"),
                    str(src)], check=True, capture_output=True, cwd=tmp_path)
    wheel = next((tmp_path / "dist").glob("*.whl"))
    subprocess.run([*pip, "--python", str(py), "install", "--quiet", "--no-deps", str(wheel)], check=True,
                   capture_output=True, cwd=tmp_path)
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                               check=True, capture_output=True, text=True).stdout.strip())
    top = {p.name for p in site.iterdir()
           if not p.name.endswith((".dist-info", ".pth")) and p.name != "__pycache__"}
    assert top == {"rig"}, top
    assert {p.name for p in (site / "rig").iterdir()} >= {"drivers", "sim", "control", "specs"}
    # run from elsewhere than the checkout: what an installed user meets
    probe = ("import importlib.util as u; "
             "print([u.find_spec(n) is not None for n in ('rig.drivers.base', 'rig.sim.params', "
             "'drivers', 'sim_device')])")
    out = subprocess.run([str(py), "-c", probe], check=True, capture_output=True, text=True, cwd=tmp_path)
    assert out.stdout.strip() == "[True, True, False, False]", out.stdout


def test_a_source_checkout_imports_the_same_names():
    """Run from the checkout without installing (the folders at the root), `rig.drivers` and
    `rig.sim` are the root folders `drivers/` and `sim_device/`."""
    probe = "import rig.drivers.base, rig.sim.params; print(rig.drivers.__file__); print(rig.sim.__file__)"
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True, cwd=ROOT)
    drivers, sim = (Path(line).resolve() for line in out.stdout.split())
    assert (drivers, sim) == (ROOT / "drivers" / "__init__.py", ROOT / "sim_device" / "__init__.py")
