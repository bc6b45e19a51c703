"""Drawing only: the sidebar panels and the plot preview (they draw ``settings``; never import ``operators``)."""

from .panel import (
    VIEW3D_PT_hybrid_raycast,
    VIEW3D_PT_hybrid_raycast_figures,
    VIEW3D_PT_hybrid_raycast_parts,
    VIEW3D_PT_hybrid_raycast_points,
    VIEW3D_PT_hybrid_raycast_settings,
    VIEW3D_PT_hybrid_raycast_trace,
)

classes = (
    VIEW3D_PT_hybrid_raycast,
    VIEW3D_PT_hybrid_raycast_figures,
    VIEW3D_PT_hybrid_raycast_parts,
    VIEW3D_PT_hybrid_raycast_points,
    VIEW3D_PT_hybrid_raycast_settings,
    VIEW3D_PT_hybrid_raycast_trace,
)
