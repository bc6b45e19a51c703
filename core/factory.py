"""``build(mesh, kind)``: the one way to make a structure.

It sits above the structures (each of which imports ``Accel`` from ``accel.py``), so
imports run one way: factory -> structures -> accel.
"""

from __future__ import annotations

from .accel import Accel
from .mesh import TriangleMesh

KINDS = ("grid", "bvh", "embree", "brute")


def build(mesh: TriangleMesh, kind: str = "bvh", **config) -> Accel:
    """Build the structure ``kind`` ('grid', 'bvh', 'embree' or 'brute') over ``mesh``.

    ``config`` goes to the structure (each documents its knobs and their defaults),
    plus ``threads`` and ``chunk_size`` which every structure takes.
    """
    kind = str(kind).lower()
    if kind == "brute":
        from .brute import BruteForce as cls
    elif kind == "grid":
        from .grid import UniformGrid as cls
    elif kind == "bvh":
        from .bvh import BVH as cls
    elif kind == "embree":
        from .embree import EmbreeAccel as cls
    else:
        raise ValueError(f"unknown structure kind {kind!r}; expected one of {', '.join(KINDS)}")
    return cls(mesh, **config)


def unavailable_reason(kind: str) -> str | None:
    """Why ``kind`` cannot be built here (one line), or None when it can."""
    from . import embree

    if kind == "embree" and not embree.embree_available():
        why = getattr(embree, "embree_unavailable_reason", None)
        return (why() if why is not None else None) or "embreex is not installed"
    return None


def available_kinds(kinds) -> tuple[tuple[str, ...], list[str]]:
    """The kinds that can be built here, and a note for each one that cannot."""
    keep, notes = [], []
    for k in kinds:
        why = unavailable_reason(k)
        if why:
            notes.append(f"{k} skipped: {why}")
        else:
            keep.append(k)
    return tuple(keep), notes
