"""Shared test set-up.

The repository root *is* the extension package.  Tests import it as ``hybrid_raycast``
without running its ``__init__`` (which needs bpy), so core tests run anywhere;
Blender tests import the full add-on through ``load_addon()``.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT.parent / "shared" / "scenes"

if "hybrid_raycast" not in sys.modules:
    pkg = types.ModuleType("hybrid_raycast")
    pkg.__path__ = [str(ROOT)]
    pkg.__file__ = str(ROOT / "__init__.py")
    sys.modules["hybrid_raycast"] = pkg


def load_addon(name: str = "hybrid_raycast_addon"):
    """Import the whole add-on (``__init__`` included) under ``name``; needs bpy."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "__init__.py", submodule_search_locations=[str(ROOT)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def real_scene_paths():
    return sorted(SCENES.glob("*.obj")) if SCENES.is_dir() else []


@pytest.fixture(scope="session")
def scenes_dir():
    if not SCENES.is_dir():
        pytest.skip(f"real meshes not found at {SCENES} (../shared/scenes beside the project); skipping")
    return SCENES


def pytest_configure(config):
    config.addinivalue_line("markers", "blender: needs bpy (Blender as a Python module)")
    config.addinivalue_line("markers", "slow: takes more than a few seconds")
