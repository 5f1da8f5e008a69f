"""indentation-rig: controller and model lab for a soft-tissue indentation rig.

The drivers and the simulated rig are the root folders `drivers/` and `sim_device/`, imported
as `rig.drivers` and `rig.sim`: an installed package holds them inside (setuptools'
`package-dir` in pyproject.toml); run from a source checkout, the finder below maps the two
names onto the folders, as an editable install does.
"""

import importlib.util
import sys
from pathlib import Path

__version__ = "0.1.0"

_HERE = Path(__file__).resolve().parent
_FOLDERS = {"rig.drivers": _HERE.parent / "drivers", "rig.sim": _HERE.parent / "sim_device"}


class _SourceCheckout:
    """Finds `rig.drivers` and `rig.sim` in the root folders when they are not inside the package."""

    @staticmethod
    def find_spec(name: str, path=None, target=None):
        folder = _FOLDERS.get(name)
        if folder is None or not (folder / "__init__.py").is_file():
            return None
        return importlib.util.spec_from_file_location(name, folder / "__init__.py",
                                                      submodule_search_locations=[str(folder)])


if not (_HERE / "drivers").is_dir():  # a source checkout, not an installed package
    # First, not last: an editable install of another checkout maps the same two names to its
    # own folders, and this checkout's `rig` must not run with that checkout's drivers.
    sys.meta_path.insert(0, _SourceCheckout)
