"""The bridge between Blender and core: extraction, the operators, the CLI.

Operators: ``hybrid_raycast.analyze``, ``.trace`` (camera passes / AO bake),
``.calibrate``, ``.bake_proximity`` and ``.scene_summary`` (extraction only).
"""

from .analyze import HYBRID_RAYCAST_OT_analyze
from .calibrate import HYBRID_RAYCAST_OT_calibrate
from .proximity import HYBRID_RAYCAST_OT_bake_proximity
from .summary import HYBRID_RAYCAST_OT_scene_summary
from .trace import HYBRID_RAYCAST_OT_trace

classes = (
    HYBRID_RAYCAST_OT_scene_summary,
    HYBRID_RAYCAST_OT_analyze,
    HYBRID_RAYCAST_OT_trace,
    HYBRID_RAYCAST_OT_calibrate,
    HYBRID_RAYCAST_OT_bake_proximity,
)
