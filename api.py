"""Script API: cast rays into the evaluated scene, with what ``scene.ray_cast`` gives, in arrays.

    from bl_ext.user_default.hybrid_raycast import api      # installed extension
    r = api.cast(origins, directions)                       # (M, 3) or (3,), world space
    r.t, r.hit, r.points, r.normals
    r.objects[r.object_index[r.hit]]                        # the bpy.types.Object hit
    api.occluded(origins, directions, tmax=1.0)             # (M,) bool: anything in the way
    api.cast_all(origins, directions, max_hits=8)           # every hit, flat, by ray then t
    c = api.closest(points)                                 # nearest surface point: c.distance, c.points, ...
    api.inside(points), api.signed_distance(points)         # winding number > 0.5; negative inside
    api.count_hits(origins, directions)                     # (M,) hits along each ray

Every call goes through the session of the depsgraph's scene and view layer
(``operators/session.py``; the queries themselves are in ``operators/query.py``): the
triangles, the structures and the plan are reused while
the scene's fingerprint is unchanged, and extracted again otherwise, so a cast always sees
the scene as it is now.  The first cast plans (``core.plan``: the grid, K sample rays from
the cast, the paper's rule for ``expected_rays``); later casts reuse the chosen structure
and leave the grid once the rays of all casts pass the break-even or the grid's
accumulated time reaches the estimated build (``core.ski_rental``).  ``structure=`` forces
one.  Rays are traced in chunks of ``CHUNK``: ``progress(done, total)`` is called after
each, the window manager's progress bar moves in the GUI, and Ctrl-C (KeyboardInterrupt)
stops the cast without a result.
"""

from __future__ import annotations

import importlib

#: where each name lives: the queries in ``operators/query.py``, the scans in
#: ``operators/scan.py``.  Both need bpy, so they are imported on first use (PEP 562) and a
#: plain ``import hybrid_raycast`` (the core without Blender) never imports bpy
_HOMES = {**{n: "query" for n in ("CastResult", "AllHits", "ClosestResult", "cast", "occluded", "cast_all", "closest",
                                   "inside", "signed_distance", "count_hits", "STRUCTURES", "CHUNK")},
          **{n: "scan" for n in ("ScanResult", "scan")}}

__all__ = ["CastResult", "AllHits", "ClosestResult", "ScanResult", "cast", "occluded", "cast_all", "closest", "inside",
           "signed_distance", "count_hits", "scan", "STRUCTURES", "CHUNK"]


def __getattr__(name):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".operators.{home}", __package__), name)


def __dir__():
    return sorted(set(globals()) | set(__all__))
