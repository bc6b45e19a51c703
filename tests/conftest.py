"""Shared test set-up.

The repository root *is* the extension package.  Tests import it as ``hybrid_raycast``
without running its ``__init__`` (which needs bpy), so core tests run anywhere;
Blender tests import the full add-on through ``load_addon()``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT.parent / "shared" / "scenes"
sys.path.insert(0, str(ROOT / "scripts"))

from _bpy_exit import exit_past_bpy  # noqa: E402
from _package import core_package, load_addon  # noqa: E402,F401  (load_addon is for Blender tests)

core_package()


def real_scene_paths():
    return sorted(SCENES.glob("*.obj")) if SCENES.is_dir() else []


@pytest.fixture(scope="session")
def scenes_dir():
    if not SCENES.is_dir():
        pytest.skip(f"real meshes not found at {SCENES} (../shared/scenes beside the project); skipping")
    return SCENES


def pytest_configure(config):
    config.addinivalue_line("markers", "blender: needs bpy (Blender as a Python module)")
    config.addinivalue_line("markers", "slow: needs a real calibration, a large scene or a zip round trip "
                                       "(make test-slow, its own CI leg; make test leaves it out)")


# bpy's exit bugs (scripts/_bpy_exit.py): leave right after pytest's last hook, when its
# summary is written, with pytest's own exit status, so a failure still exits non-zero.
_session = None


def pytest_sessionstart(session):
    global _session
    _session = session


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    if _session is not None:
        exit_past_bpy(_session.exitstatus)
