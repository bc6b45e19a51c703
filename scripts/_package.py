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
#: the real meshes for evaluation and benchmarks, beside the repository (never copied into it)
SHARED_SCENES = ROOT.parent / "shared" / "scenes"


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


def importable_by_workers() -> str:
    """Make ``import hybrid_raycast`` find this checkout in processes started from here
    (Dask's worker processes): a temporary folder holding a ``hybrid_raycast`` symlink to
    the root goes on sys.path (which spawned processes inherit) and PYTHONPATH.  Once per
    process; removed at exit.  An installed package (``pip install .``) needs none of this."""
    global _WORKER_PATH
    if _WORKER_PATH is None:
        import atexit
        import os
        import shutil
        import tempfile

        _WORKER_PATH = tempfile.mkdtemp(prefix="hrc-pkg-")
        os.symlink(ROOT, os.path.join(_WORKER_PATH, "hybrid_raycast"))
        atexit.register(shutil.rmtree, _WORKER_PATH, True)
        sys.path.append(_WORKER_PATH)
        os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, (os.environ.get("PYTHONPATH"), _WORKER_PATH)))
    return _WORKER_PATH


_WORKER_PATH = None
