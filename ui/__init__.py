"""Drawing only: the sidebar panels, the scene properties they show, the plot."""

from .panel import (
    VIEW3D_PT_hybrid_raycast,
    VIEW3D_PT_hybrid_raycast_figures,
    VIEW3D_PT_hybrid_raycast_settings,
    VIEW3D_PT_hybrid_raycast_trace,
)

classes = (
    VIEW3D_PT_hybrid_raycast,
    VIEW3D_PT_hybrid_raycast_figures,
    VIEW3D_PT_hybrid_raycast_settings,
    VIEW3D_PT_hybrid_raycast_trace,
)
