"""Drawing only: the sidebar panel and the scene properties it shows."""

from .panel import VIEW3D_PT_hybrid_raycast

classes = (VIEW3D_PT_hybrid_raycast,)
