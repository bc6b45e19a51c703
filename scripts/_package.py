"""Import this repository as the ``hybrid_raycast`` package from scripts and tests.

The repository root is the extension package.  ``core_package()`` makes
``import hybrid_raycast.core`` work without running the root ``__init__`` (no bpy
needed); ``load_addon()`` runs the root ``__init__`` into that same module (bpy needed).
"""

import importlib.util
import sys
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def core_package(name: str = "hybrid_raycast"):
    if name not in sys.modules:
        pkg = types.ModuleType(name)
        pkg.__path__ = [str(ROOT)]
        pkg.__file__ = str(ROOT / "__init__.py")
        sys.modules[name] = pkg
    return sys.modules[name]


def load_addon(name: str = "hybrid_raycast"):
    """The whole add-on, ``__init__`` run into the same module, so there is one ``core``."""
    pkg = core_package(name)
    if not hasattr(pkg, "register"):
        spec = importlib.util.spec_from_file_location(name, ROOT / "__init__.py", submodule_search_locations=[str(ROOT)])
        pkg.__spec__ = spec
        spec.loader.exec_module(pkg)
    return pkg
