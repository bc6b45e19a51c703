"""Scene files per frame: what ``-c hybrid_raycast export`` writes for tracing without Blender.

Each frame is set, the depsgraph evaluated and the scene extracted as Analyze does
(visible, render-enabled triangles), then written atomically as ``frame_<number>.npz`` in
the output folder: by default instanced (``core.meshio.save_scene``, version 2: each
evaluated mesh once in object space, and every placement's matrix, object and triangle
base, from ``extract.scene_layout``), or with ``instanced=False`` flat
(``core.save_mesh``, version 1: the world-space mesh ``analyze.extract`` gives).  Both
load as the same ``TriangleMesh``.  The scene's current frame is restored afterwards,
whatever happened.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .. import core
from ..core.meshio import save_scene
from . import session
from .analyze import evaluated_depsgraph, extract
from .jobs import BadInput, HRCError, Unwritable

FILE_NAME = "frame_{frame:04d}.npz"
_RANGE = re.compile(r"^\s*(-?\d+)\s*(?:(?:-|\.\.)\s*(-?\d+)\s*)?$")


def parse_frames(text: str) -> list[int]:
    """'1-250', '7', '1-10,20,30-40' -> the frames in order, each once; BadInput otherwise."""
    frames = []
    for part in str(text).split(","):
        m = _RANGE.match(part)
        if not m:
            raise BadInput(f"bad arguments: --frames {text!r}: use N, A-B or a comma-separated list of them")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a
        if b < a:
            raise BadInput(f"bad arguments: --frames {text!r}: range {a}-{b} runs backwards")
        frames.extend(range(a, b + 1))
    return list(dict.fromkeys(frames))


def _save_layout(layout, path: Path, frame: int) -> None:
    """One version-2 file: the layout's groups once, placements in its (flat) order."""
    meshes = [core.TriangleMesh(g.co, g.tris, polygon_index=g.poly) for g in layout.groups]
    entries = np.concatenate([np.asarray(g.entries, np.int32) for g in layout.groups])  # into layout.names
    save_scene(path, meshes, layout.placement_group, layout.matrices, entries, layout.names, layout.tri_base,
               frame=frame)


def export_frames(scene, frames, out_dir: Path, *, view_layer=None, selected_only=False, progress=None,
                  instanced: bool = True) -> list[dict]:
    """Write one scene file per frame into ``out_dir``; [{frame, path, triangles, objects}].

    instanced: each mesh once with its placements (version 2, the default), or False for
    the flat world-space mesh (version 1).
    progress(done, total, record) is called after each file.  NoGeometry / InvalidGeometry
    (``operators.jobs``) name the frame; Unwritable when a file cannot be written.
    """
    original = scene.frame_current, scene.frame_subframe
    written = []
    try:
        for i, frame in enumerate(frames):
            scene.frame_set(frame)
            depsgraph = evaluated_depsgraph(scene, view_layer)
            try:
                if instanced:
                    mesh, _ = session.extract_layout(depsgraph, selected_only=selected_only, strict=True)
                else:
                    mesh, _ = extract(depsgraph, selected_only=selected_only)
            except HRCError as e:  # the same failure, with the frame it happened at
                raise type(e)(f"frame {frame}: {e}") from None
            path = out_dir / FILE_NAME.format(frame=frame)
            try:
                if instanced:
                    _save_layout(mesh, path, frame)
                else:
                    core.save_mesh(mesh, path, frame=frame)
            except OSError as e:
                raise Unwritable(f"unwritable path: {path}: {e.strerror or e}") from None
            record = {"frame": frame, "path": str(path), "triangles": mesh.triangle_count,
                      "objects": len(mesh.object_names)}
            written.append(record)
            if progress is not None:
                progress(i + 1, len(frames), record)
    finally:
        scene.frame_set(original[0], subframe=original[1])
    return written
