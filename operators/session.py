"""The session: one home for what the add-on keeps between calls, and when it is still right.

``get(depsgraph, settings)`` returns the ``Session`` of the depsgraph's scene and view
layer: the extracted triangles (``operators/extract.py``), the structures built over them,
the plan of the first cast and the grid's running totals for the online rule.  ``api``,
the Trace operator and the Analyze operator all go through it.

Right by construction: a session is reused only while its *fingerprint* is equal to the
fingerprint of the depsgraph asked about, computed at every ``get``.  No update handler
decides what is current, so handler order or a missed update cannot serve old triangles.
The fingerprint is:
- head: the scene, the view layer, the depsgraph mode, the selected-only setting (not the
  frame: what a frame changes shows in the body, so a frame where nothing moved keeps the
  session, its extraction and its structures);
- body: per evaluated object of ``depsgraph.ids`` that can bring triangles (not cameras,
  lights, probes, speakers, armatures, nor Empties that instance nothing; instanced-only
  objects included): its original,
  name, type, the ``session_uid`` of its evaluated data (Blender gives an evaluated mesh a
  new one every time it is evaluated again: an edit, a modifier, geometry nodes, a
  driver; checked with bpy 5.0.1), its world matrix, visibility in the view layer,
  ``hide_render``, selection (with selected-only), ``show_instancer_for_render`` and its
  instancing; and per layer collection its exclude, viewport and render flags.
Geometry-nodes and particle instances are not listed one by one: they are part of their
instancer's evaluation, whose data gets a new ``session_uid`` when they change.  Its cost
is small per object and does not grow with the number of instances (BENCHMARKS.md,
"Script API per call").

The sidebar's stale flag uses the same fingerprint: the analysis remembers the body it
was made on, and ``on_depsgraph_update`` (on ``depsgraph_update_post`` and
``frame_change_post``) compares
the current one, setting ``scene.hybrid_raycast.geometry_changed``.  The frame is left
out of that comparison (a frame change that moves nothing leaves the analysis right);
the add-on's own writes (the AO bake's colour attribute) are adopted by
``adopt_own_write``.  Loading a file clears every session.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from dataclasses import dataclass, field

import bpy
import numpy as np
from bpy.app.handlers import persistent

from .. import core, settings
from ..core.mesh import unit_normals
from .extract import NoGeometryError, forget, scene_layout, scene_summary
from .jobs import InvalidGeometry, NoGeometry

#: (scene pointer, view layer pointer, selected_only) -> Session
SESSIONS: dict[tuple, "Session"] = {}
#: scene pointer -> (view layer pointer, selected_only, body) of the analysis shown in the sidebar
ANALYSED: dict[int, tuple] = {}

# looked up once: an attribute of bpy.types costs tens of microseconds per access
_DEPSGRAPH = bpy.types.Depsgraph
_OBJECT = bpy.types.Object
_NOT_GEOMETRY = frozenset({"CAMERA", "LIGHT", "LIGHT_PROBE", "LIGHTPROBE", "SPEAKER", "ARMATURE"})
_adopting = False


# -- the fingerprint ---------------------------------------------------------------------

def _layer_flags(vl) -> tuple:
    out, stack = [], [vl.layer_collection]
    while stack:
        lc = stack.pop()
        out.append((lc.collection.as_pointer(), lc.exclude, lc.hide_viewport, lc.collection.hide_render,
                    lc.collection.hide_viewport))
        stack.extend(lc.children)
    return tuple(out)


def fingerprint(depsgraph, selected_only: bool = False) -> tuple[tuple, tuple]:
    """(head, body) of what the extraction of ``depsgraph`` depends on (module doc)."""
    scene, vl = depsgraph.scene, depsgraph.view_layer
    head = (scene.as_pointer(), vl.as_pointer(), depsgraph.mode, bool(selected_only))
    body = [_layer_flags(vl)]
    for idb in depsgraph.ids:
        if not isinstance(idb, _OBJECT) or idb.type in _NOT_GEOMETRY:
            continue
        if idb.type == "EMPTY" and idb.instance_type == "NONE":  # places nothing (a parent's motion shows in its children)
            continue
        orig = idb.original
        data = idb.data
        try:
            visible = orig.visible_get(view_layer=vl)
            selected = orig.select_get(view_layer=vl) if selected_only else False
        except RuntimeError:  # not in this view layer: only instanced
            visible = selected = None
        coll = idb.instance_collection
        body.append((orig.as_pointer(), orig.name, idb.type, data.session_uid if data is not None else 0,
                     EDITS.get(orig.as_pointer(), 0),
                     idb.matrix_world.copy(), visible, selected, orig.hide_render, orig.show_instancer_for_render,
                     idb.instance_type, coll.as_pointer() if coll is not None else 0))
    return head, tuple(body)


def check_depsgraph(depsgraph, name="depsgraph"):
    if not isinstance(depsgraph, _DEPSGRAPH):
        raise TypeError(f"{name} must be a bpy.types.Depsgraph (e.g. context.evaluated_depsgraph_get()), "
                        f"got {type(depsgraph).__name__}")
    return depsgraph


# -- extraction with one-line errors -------------------------------------------------------

def _non_finite_objects(depsgraph) -> list[tuple[str, int]]:
    """(object name, vertices with NaN/inf coordinates) of the evaluated meshes."""
    bad, seen = [], set()
    for inst in depsgraph.object_instances:
        ob = inst.object
        if ob.type != "MESH" or ob.data is None or ob.data.as_pointer() in seen:
            continue
        seen.add(ob.data.as_pointer())
        me = ob.data
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        n = int((~np.isfinite(co.reshape(-1, 3)).all(axis=1)).sum())
        if n:
            bad.append((ob.name, n))
    return bad


def extract(depsgraph, *, selected_only=False, progress=None, attributes=()):
    """(flat TriangleMesh, summary dict) of the evaluated scene; NoGeometry or
    InvalidGeometry (also for NaN or infinite vertices) with a one-line reason."""
    t0 = time.perf_counter()
    layout, _ = extract_layout(depsgraph, selected_only=selected_only, progress=progress, attributes=attributes,
                               strict=True)
    mesh = layout.flat(progress)
    return mesh, scene_summary(depsgraph, mesh, time.perf_counter() - t0)


def extract_layout(depsgraph, *, selected_only=False, progress=None, attributes=(), cache=None, strict=False):
    """(``extract.Layout``, summary dict without bounds) of the evaluated scene; with
    ``cache`` (``MESHES``), every mesh whose key is there is taken from it.  NoGeometry, or
    InvalidGeometry when every triangle has a NaN or infinite corner, or with ``strict`` when
    any has; otherwise such triangles are left out (``layout.left_out``)."""
    t0 = time.perf_counter()
    try:
        layout = scene_layout(depsgraph, selected_only=selected_only, progress=progress, attributes=attributes,
                              cache=cache, edits=EDITS if cache is not None else None)
    except NoGeometryError as e:
        raise NoGeometry(f"no geometry: {e}") from None
    except ValueError:  # every triangle had a NaN or infinite corner
        raise InvalidGeometry(_invalid_message(depsgraph)) from None
    if strict and layout.left_out:
        raise InvalidGeometry(_invalid_message(depsgraph))
    if progress is not None:
        progress(1.0)
    return layout, scene_summary(depsgraph, layout, time.perf_counter() - t0, bounds=False)


def _invalid_message(depsgraph) -> str:
    bad = _non_finite_objects(depsgraph)
    names = ", ".join(f"'{n}' ({k} vertices)" for n, k in bad[:5]) or "an evaluated mesh"
    return f"invalid geometry: NaN or infinite vertex coordinates in {names}; fix or hide them"


def left_out_message(left_out) -> str:
    """One line naming the sources whose NaN or infinite triangles were left out, and how many."""
    parts = [f"{', '.join(repr(n) for n in names)}: {count:,} triangles" for names, count in left_out[:5]]
    more = f" and {len(left_out) - 5} more meshes" if len(left_out) > 5 else ""
    return f"left out triangles with NaN or infinite vertex coordinates ({'; '.join(parts)}{more})"


# -- the session ---------------------------------------------------------------------------

#: mesh key (``extract.mesh_key``) -> ``extract.MeshRead``: every evaluated mesh a live
#: session uses, in object space, so a new session reads only the meshes that changed
MESHES: dict = {}
#: (mesh key, kind, config items) -> the bottom-level structure over that mesh in object
#: space: built once, shared by every session (frame) that places the mesh
BOTTOMS: dict = {}
#: (kind, config items, the still placements' identities) -> (flat structure over their world
#: triangles, global, instance, local per triangle): the part of a changing scene that stays put
SOUPS: dict = {}
#: soups kept (a few: the scenes and kinds in use)
SOUPS_KEPT = 4
#: how many times instancing must multiply the unique triangles for a scene to be traced on
#: two levels from its first call (``Session.instanced``)
INSTANCED_FROM = 8
#: what each lasting part has served, for the rule over its life (``Session._life_choice``):
#: ('soup', still placements' identities) or ('bottom', mesh key) -> rays
LIFE: dict = {}
#: the calls a job still expects (``expecting``), None outside a job that said
JOB: list = [None]
#: the timings of the last call, per session: what the call paid for
TIMING_KEYS = ("extract", "bottom_builds", "top_level", "trace")


#: the scene summary's words for moved placements rebuilt flat
MOVED_FLAT = "moved, and fewer triangles than the call's rays passing near it: rebuilt flat"


@dataclass(eq=False)
class Session:
    """One scene + view layer's extraction, its structures and its running totals.

    ``layout`` is the extraction as meshes and placements; ``mesh`` the flat world-space
    ``TriangleMesh``, assembled from it on first use."""

    key: tuple
    head: tuple
    body: tuple
    layout: object
    _summary: dict
    attributes: frozenset = frozenset()
    #: (kind, sorted config items) -> Accel
    structures: dict = field(default_factory=dict)
    #: structures' key -> why its moved placements were rebuilt flat (the scene summary's words)
    rebuilt_why: dict = field(default_factory=dict)
    #: the auto structure's key -> its parts' choices, in the Split's order (the soups, then
    #: each bottom level): ``_life_choice``'s dicts with 'what' and 'triangles'
    choices: dict = field(default_factory=dict)
    #: the plan of the first cast (``api``), and of the analysis when it made this session
    plan: object = None
    analysis_plan: object = None
    #: the structure later auto casts use: None before the first plan, then 'grid' until
    #: the online rule switches
    chosen: str | None = None
    #: what the grid has traced for auto casts so far (the online rule's state)
    grid_time: float = 0.0
    grid_rays: int = 0
    calibration: object = None
    kinds: tuple = ()
    #: the last closest-point query's plan (``core.decide.points.PointPlan``; None before one)
    point_plan: object = None
    #: whether this session replaced an earlier one of the same scene (the scene changes between calls)
    changed: bool = False
    #: (I,) bool: placements the previous session had too, with the same mesh and matrix
    still: object = None
    #: a rigid sweep (``swept``): (the layout traced, its (K, I, 4, 4) matrices at K instants)
    sweep: object = None
    #: seconds the last call paid: extraction, bottom builds, top level, trace (``TIMING_KEYS``)
    timings: dict = field(default_factory=lambda: dict.fromkeys(TIMING_KEYS, 0.0))
    #: per triangle, the world-space unit geometric normal (float32), made on first use
    _normals: object = None
    _per_triangle: object = None
    _tables: object = None
    _described: object = None
    _materials: object = None

    @property
    def mesh(self):
        """The flat world-space ``TriangleMesh`` (``extract.Layout.flat``)."""
        return self.layout.flat()

    @property
    def instanced(self) -> bool:
        """Whether instancing multiplies the scene's triangles by ``INSTANCED_FROM`` or more
        over many placements (geometry-nodes scattering): then the scene is traced on two
        levels from its first call, as a flat soup would hold every copy in memory (and a
        numpy top level costs per ray what the copies save: BENCHMARKS.md, "Two-level
        scenes"), and 'auto' takes the fastest candidate per ray without a plan, whose
        sample needs the flat soup."""
        lay = self.layout
        unique = sum(len(g.tris) for g in lay.groups)
        return len(lay.placement_group) >= core.twolevel.PAIRS_FROM and lay.triangle_count >= INSTANCED_FROM * unique

    @property
    def summary(self) -> dict:
        """``extract.scene_summary`` of the extraction, its bounds made on first use."""
        if "bounds" not in self._summary:
            self._summary["bounds"] = [x.tolist() for x in self.layout.bounds()]
        return self._summary

    def tracer(self, kind: str, rays=None, batch=None, *, auto=False, grid_config=None, **config):
        """What traces with ``kind``: the flat structure while the scene has not changed
        since its first call; after a change, a ``core.Split``: a flat structure over the
        placements that stayed put (built once while they do, shared by the sessions that
        follow), the moved ones either as a flat structure rebuilt now or on two levels
        (``core.TwoLevel``: one bottom level per unique mesh, built once in object space,
        under a top level over their placements).

        The lines between them are the paper's decision on each structure's life: a scene
        that stays put keeps its first session, where one flat structure traces fastest (a
        top level costs per ray; BENCHMARKS.md, "Two-level scenes"); a mesh read afresh
        (deformed, edited, new) is rebuilt flat, as it must be built anyway; a moved mesh
        kept from before is rebuilt flat when it has fewer triangles than the rays its top
        level would take (the build is linear in triangles, the top level in rays), else
        placed on two levels, whose bottom is built once for every frame that moves it.
        Those rays: of the session's first batch (``rays``: the rays until the next change,
        as far as is known), for a few moved placements only those passing near them
        (``_rays_near``: the loop top level tests nothing else), estimated on a sample of
        ``batch`` (origins, directions, tmin, tmax).

        ``auto``: each part picks its own structure by the rule over its life
        (``_life_choice``): the still soup and each bottom level for the rays they are
        expected to serve until they change, a part rebuilt this call for this call's rays;
        ``kind`` is then the fallback where the calibration cannot price a part, and
        ``grid_config`` the grid's settings."""
        if not self.changed and not self.instanced:
            return self.structure(kind, **config)
        grid_config = dict(grid_config or {})
        k = self.auto_key(grid_config) if auto else ("twolevel", kind, tuple(sorted(config.items())))
        acc = self.structures.get(k)
        if acc is not None:
            return acc
        lay = self.traced_layout
        still = self.still if self.still is not None else np.zeros(len(lay.placement_group), bool)
        moving = np.flatnonzero(~still)
        near = why = None
        sizes = np.array([len(g.tris) for g in lay.groups], np.int64)
        # with auto, each part's choice (``_life_choice``), in the Split's order: the soups, then each bottom
        info = []

        def pick_for(tris, life_key, built, near, lasting, what):
            if not auto:
                return kind, dict(config)
            c = self._life_choice(kind, int(tris), rays, near, life_key, built, lasting)
            c.update(what=what, triangles=int(tris))
            info.append(c)
            return c["kind"], (grid_config if c["kind"] == "grid" else {})

        t0 = time.perf_counter()
        soups, two = [], None
        if still.any():
            placements = np.flatnonzero(still)
            ident = self._soup_ident(placements)
            built = {kk for (kk, _c, i) in SOUPS if i == ident}
            sk, sc = pick_for(sizes[lay.placement_group[placements]].sum(), ("soup", ident), built, rays, True,
                              "the placements that stayed put")
            soups.append(self._soup(sk, sc, placements, ident))
            if soups[-1] is None and auto:
                info.pop()
        if len(moving) and self.sweep is None:
            # after a change, a mesh read afresh (deforming, edited, new) is built now
            # whatever its form: flat, as that traces fastest (an instanced scene keeps its
            # copies on two levels); a moved mesh kept from before, when it has fewer
            # triangles than the rays passing near it
            fresh = np.array([lay.groups[g].fresh for g in lay.placement_group[moving].tolist()], bool) \
                if self.changed and not self.instanced else np.zeros(len(moving), bool)
            kept_tris = int(sizes[lay.placement_group[moving[~fresh]]].sum())
            near = self._rays_near(lay, moving[~fresh], rays, batch) if (~fresh).any() and rays is not None else None
            flat = fresh.copy()
            if near is not None and kept_tris <= near:
                flat[:] = True
            if flat.any():
                mesh, glob, inst, local = lay.soup(moving[flat])
                why = (MOVED_FLAT if (flat & ~fresh).any() else
                       "read afresh this call (deformed, edited or new): rebuilt flat")
                fk, fc = pick_for(len(glob), None, (), self._rays_near(lay, moving[flat], rays, batch)
                                  if auto and rays is not None else None, False, "rebuilt this call")
                soups.append((core.build(mesh.prepare(), fk, **fc), glob, inst, local))
                moving = moving[~flat]
        t1 = time.perf_counter()
        if len(moving):
            groups = np.unique(lay.placement_group[moving])
            if near is None and self.sweep is None:
                near = rays
            bottoms = {}
            for gi in groups.tolist():
                g = lay.groups[gi]
                built = {kk for (key, kk, _c) in BOTTOMS if key == g.key} if g.key is not None else set()
                bk, bc = pick_for(sizes[gi], ("bottom", g.key) if g.key is not None else None, built,
                                  rays if self.sweep is not None else near, g.key is not None,
                                  f"the mesh of '{self._group_name(lay, gi)}', on two levels" if auto else "")
                bottoms[gi] = self._bottom(g, bk, bc)
            t1 = time.perf_counter()
            order = {gi: n for n, gi in enumerate(bottoms)}
            two = core.TwoLevel([bottoms[gi] for gi in order],
                                np.array([order[int(g)] for g in lay.placement_group[moving]], np.int32),
                                lay.matrices[moving], lay.tri_base[moving])
            if self.sweep is not None:  # each ray meets the movers at its own instant
                two = core.Swept(two, self.sweep[1][:, moving])
        acc = self.structures[k] = core.Split([p for p in soups if p is not None], moving=two,
                                              moving_instances=moving if two is not None else None)
        if why is not None:
            self.rebuilt_why[k] = why
        if auto:
            self.choices[k] = info
            settings.PARTS[self._summary.get("scene", "")] = self.describe()
        self.timings["bottom_builds"] += t1 - t0
        self.timings["top_level"] += time.perf_counter() - t1
        return acc

    @staticmethod
    def auto_key(grid_config) -> tuple:
        """The key of the structure whose parts chose their own kinds (``tracer(auto=True)``)."""
        return ("twolevel", "auto", tuple(sorted(dict(grid_config or {}).items())))

    def _life_estimates(self, n: int) -> dict:
        """{kind: ``decide.Cost``} for an N-triangle part: the grid from the calibration's
        scenes, the candidates from its fitted models, each per-ray time scaled by what the
        session's plan measured on this scene against the same estimate at its size (the
        scene at hand anchors the calibration's figures)."""
        cal = self.calibration
        if cal is None:
            return {}
        p = self.plan
        out = {}
        g = cal.grid_estimate(n)
        if g is not None:
            ref = cal.grid_estimate(p.triangles) if p is not None and p.grid_built and p.grid_per_ray > 0 else None
            f = p.grid_per_ray / ref.per_ray if ref is not None and ref.per_ray > 0 else 1.0
            out["grid"] = core.decide.Cost.point("grid", g.build_time, g.per_ray * f)
        for kind in core.factory.available_kinds([k for k in self.kinds if k in cal.fits])[0]:
            e = cal.estimate(kind, n)
            c = p.candidates.get(kind) if p is not None else None
            ref = cal.estimate(kind, p.triangles) if c is not None else None
            f = c.per_ray / ref.per_ray if ref is not None and ref.per_ray > 0 and c.per_ray > 0 else 1.0
            out[kind] = core.decide.Cost.point(kind, e.build_time, e.per_ray * f)
        return out

    def _life_choice(self, kind, tris, rays, near, life_key, built, lasting) -> dict:
        """The rule over a part's life (``decide.over_life``) for a part of ``tris``
        triangles that ``near`` of this call's ``rays`` pass near.  A part rebuilt this
        call (``lasting`` False) lives for this call; one kept while it stays the same (the
        still soup, a bottom level) for the job's calls when a job said how many
        (``expecting``), else for as many rays again as it has served (``LIFE``): the
        ski-rental rule across calls, never worse than about twice the best choice in
        hindsight.  ``kind`` where nothing can be priced."""
        ests = self._life_estimates(tris)
        now = float(near if near is not None else (rays or 0))
        served = LIFE.get(life_key, 0.0) if life_key is not None else 0.0
        if not lasting:
            life, how = now, "this call, as it is rebuilt when it changes"
        elif JOB[0] is not None:
            life, how = now * JOB[0], f"the job's {JOB[0]:,} calls to come"
        else:
            life, how = now + served, (f"this call and as many again as the {served:,.0f} rays it has served "
                                       "(the ski-rental rule)" if served else
                                       "this call, its first (each call it serves raises it: the ski-rental rule)")
        if not ests:
            return {"kind": kind, "life_key": life_key, "share": now / rays if rays else 0.0, "rays": life,
                    "life": how, "why": "no calibration prices this part: the session's structure"}
        pick, totals, be, be_kind = core.decide.over_life(ests, life, built)
        words = f"the least predicted total for {life:,.0f} rays over its life: {how}"
        return {"kind": pick, "life_key": life_key, "share": now / rays if rays else 0.0, "rays": life, "life": how,
                "totals": totals, "built": sorted(built), "break_even": be, "break_even_kind": be_kind, "why": words}

    def served(self, key, m: int):
        """Count ``m`` more rays of this session against the parts of its structure ``key``
        (``LIFE``, what the rule over a part's life weighs next)."""
        for c in self.choices.get(key, ()):
            if c["life_key"] is not None:
                LIFE[c["life_key"]] = LIFE.get(c["life_key"], 0.0) + c["share"] * m

    @staticmethod
    def _group_name(lay, gi) -> str:
        first = int(np.flatnonzero(lay.placement_group == gi)[0])
        try:
            return lay.instances.objects[lay.instances.instance_object[first]].name
        except (ReferenceError, IndexError):
            return "?"

    #: rays of a batch sampled to estimate how many pass near the moved placements
    NEAR_SAMPLE = 4096

    @staticmethod
    def _rays_near(lay, moving, rays: int, batch) -> float:
        """How many of ``rays`` a top level over the ``moving`` placements would take: all
        of them on the tree path (``core.twolevel.PAIRS_FROM`` placements and more), else
        those passing near a placement's box (``core.twolevel.near_rays``), estimated on
        every k-th ray of ``batch``."""
        if batch is None or len(moving) >= core.twolevel.PAIRS_FROM:
            return rays
        o, d, tmin, tmax = (np.asarray(x) for x in batch)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        n = max(len(o), len(d))
        pick = slice(None, None, max(1, n // Session.NEAR_SAMPLE))
        one = core.twolevel.one_origin(o)
        d_s = np.broadcast_to(d, (n, 3))[pick]
        o_s = np.broadcast_to(o[:1] if one else np.broadcast_to(o, (n, 3))[pick], d_s.shape)
        sample = core.prepare_rays(o_s, d_s, tmin if tmin.ndim == 0 else tmin[pick],
                                   tmax if tmax.ndim == 0 else tmax[pick], shear=False)
        # each moved placement's world box: its mesh's object box (a kept mesh read's is computed
        # once, ``TriangleMesh.bounds``) through its matrix
        placed = [i for i in moving.tolist() if len(lay.groups[lay.placement_group[i]].tris)]
        if not placed:
            return 0.0
        groups = [lay.groups[lay.placement_group[i]] for i in placed]
        boxes = [(g.read.local_mesh() if g.read is not None else core.TriangleMesh(g.co, g.tris)).bounds() for g in groups]
        lo, hi = core.twolevel.placed_boxes([b[0] for b in boxes], [b[1] for b in boxes], lay.matrices[placed])
        near = core.twolevel.near_rays(sample, *core.twolevel.balls(lo, hi), one)
        return near.size * rays / len(sample)

    @property
    def traced_layout(self):
        """The layout the structures are built over: ``layout``, or a sweep's first instant."""
        return self.layout if self.sweep is None else self.sweep[0]

    def _soup_ident(self, placements) -> tuple:
        """What a still soup is made of: its placements' meshes, matrices and first triangles."""
        lay = self.traced_layout
        return tuple((lay.groups[lay.placement_group[i]].key, lay.matrices[i].tobytes(), int(lay.tri_base[i]))
                     for i in placements.tolist())

    def _soup(self, kind, config, placements, ident):
        """The flat structure over the still placements' world triangles, shared by the
        sessions of a scene while the same placements stay put."""
        lay = self.traced_layout
        key = (kind, tuple(sorted(config.items())), ident)
        got = SOUPS.pop(key, None)
        if got is None:
            made = lay.soup(placements)
            if made is None:
                return None
            mesh, glob, inst, local = made
            got = (core.build(mesh.prepare(), kind, **config), glob, inst, local)
            got[0]._kept = True  # kept across sessions: its normals are worth making whole
        SOUPS[key] = got  # the newest last
        while len(SOUPS) > SOUPS_KEPT:
            SOUPS.pop(next(iter(SOUPS)))
        return got

    def describe(self) -> dict:
        """How this session's scene is traced, in words and counts (for results and the
        JSON): the parts of its structures, what each holds, and why it is built so; made
        again only when the session builds another structure."""
        if self._described is not None and self._described[0] == tuple(self.structures):
            return self._described[1]
        out = self._describe()
        self._described = (tuple(self.structures), out)
        return out

    def _describe(self) -> dict:
        lay = self.layout
        unique = int(sum(len(g.tris) for g in lay.groups))
        out = {"placements": int(len(lay.placement_group)), "meshes": len(lay.groups),
               "triangles": int(lay.triangle_count), "unique_triangles": unique, "parts": []}
        still_first = self.still is not None and bool(self.still.any())  # the still soup comes first
        for key, acc in self.structures.items():
            if key[0] != "twolevel":
                continue
            choices = [_choice_dict(c) for c in self.choices.get(key, ())]  # the soups', then each bottom's
            for i, (soup, glob, inst, _loc) in enumerate(acc.soups):
                still = i == 0 and still_first
                out["parts"].append({  # a soup holds whole placements in order: count the runs
                    "kind": soup.kind, "form": "flat",
                    "placements": int(np.count_nonzero(np.diff(inst)) + 1) if len(inst) else 0,
                    "triangles": int(len(glob)),
                    "why": ("these placements stayed put since the last change: one flat structure, kept while "
                            "they do") if still else
                           self.rebuilt_why.get(key, MOVED_FLAT)})
                if choices:
                    out["parts"][-1]["choice"] = choices.pop(0)
            if acc.moving is not None:
                kinds = sorted({b.kind for b in getattr(acc.moving, "two", acc.moving).bottoms})
                out["parts"].append({
                    "kind": kinds[0] if len(kinds) == 1 else "mixed", "form": "two levels",
                    "placements": int(acc.moving.instance_count),
                    "triangles": int(acc.moving.triangle_count),
                    "why": (f"moved within the sweep: one structure per mesh, built once, each ray meeting it "
                            f"placed at the ray's own instant (of {len(self.sweep[1])})") if self.sweep is not None else
                           "moved, with more triangles than the call's rays passing near it: one structure per mesh, built once, "
                           "placed under a top level"})
                if choices:  # one per mesh, by the rule over its life
                    out["parts"][-1]["meshes"] = choices
        if self.instanced:
            out["instanced"] = (f"instancing multiplies {unique:,} unique triangles {lay.triangle_count / max(unique, 1):.0f}"
                                f" times over {len(lay.placement_group):,} placements: two levels from the first call")
        if not out["parts"]:
            out["parts"].append({"kind": self.chosen, "form": "flat", "placements": out["placements"],
                                 "triangles": out["triangles"],
                                 "why": "the scene has not changed since its first call: one flat structure"})
        return out

    @staticmethod
    def _bottom(g, kind, config):
        key = (g.key, kind, tuple(sorted(config.items()))) if g.key is not None else None
        acc = BOTTOMS.get(key) if key is not None else None
        if acc is None:
            local = g.read.local_mesh() if g.read is not None else core.TriangleMesh(g.co, g.tris, None, g.poly)
            acc = core.build(local.prepare(), kind, **config)
            if key is not None:
                BOTTOMS[key] = acc
        return acc

    def decode(self, h, hits_only=False):
        """Per-hit (object index, instance index, polygon index, unit world normal, u, v)
        of a two-level trace's ``core.InstanceHits``, without the flat mesh: the normal is
        the object-space one turned by the inverse transpose of the instance's matrix (a
        soup's triangles have theirs in world space already), and a mirrored instance's u
        and v trade places (the flat mesh swaps two corners there).  Each (M,) with -1 / NaN
        on a miss; ``hits_only``: (the hits' rows, then each for those rows only)."""
        poly_pool, normal_pool, base, inv, mirrored = self.layout.pools()
        got = np.flatnonzero(h.instance >= 0)
        i = np.take(h.instance, got)
        at = np.take(base, i) + np.take(h.local_triangle, got)
        obj_h = np.take(self.layout.instances.instance_object, i)
        poly_h = np.take(poly_pool, at)
        n_h = np.empty((len(got), 3), np.float32)
        u_h, v_h = np.take(h.u, got), np.take(h.v, got)
        soup = getattr(h, "soup", None)
        flat = np.zeros(len(got), bool) if soup is None else np.take(soup, got) >= 0
        if flat.any():  # a kept soup's world normals are made once with it, a rebuilt one's per hit
            pos = np.flatnonzero(flat)
            which = np.take(soup, got[pos])
            for si in np.flatnonzero(np.bincount(which, minlength=len(h.soups))).tolist():
                p = pos[which == si]
                tri = np.take(h.soup_triangle, got[p])
                acc = h.soups[si]
                if getattr(acc, "_kept", False):
                    if getattr(acc, "_normal_columns", None) is None:  # by columns: scattering rows of 3 costs more
                        acc._normal_columns = np.ascontiguousarray(unit_normals(acc.mesh.tri_vertices).T)
                    for c in range(3):
                        n_h[p, c] = np.take(acc._normal_columns[c], tri)
                else:
                    n_h[p] = unit_normals(acc.mesh.tri_vertices[tri])
        rest = np.flatnonzero(~flat)
        if rest.size:
            ir = i[rest]
            w = np.einsum("mj,mjk->mk", normal_pool[at[rest]].astype(np.float64), inv[ir])
            with np.errstate(invalid="ignore", divide="ignore"):
                w /= np.linalg.norm(w, axis=1, keepdims=True)
            n_h[rest] = w
            swap = rest[mirrored[ir]]
            u_h[swap], v_h[swap] = v_h[swap], u_h[swap].copy()
        if hits_only:
            return got, (obj_h, i, poly_h, n_h, u_h, v_h)
        m = len(h.instance)
        obj = np.full(m, -1, np.int32)
        ins = np.full(m, -1, np.int32)
        poly = np.full(m, -1, np.int32)
        n = np.full((m, 3), np.nan, np.float32)
        u, v = h.u.copy(), h.v.copy()
        obj[got], ins[got], poly[got], n[got], u[got], v[got] = obj_h, i, poly_h, n_h, u_h, v_h
        return obj, ins, poly, n, u, v

    def decode_materials(self, h, hits_only=False) -> np.ndarray:
        """(M,) int32 material index (into ``material_tables()[0]``) of two-level hits, -1
        on a miss; ``hits_only``: for the hits only, in ray order."""
        _, pool, base = self.layout.material_pool()
        got = np.flatnonzero(h.instance >= 0)
        out_h = (np.take(pool, np.take(base, h.instance[got]) + h.local_triangle[got]).astype(np.int32)
                 if len(pool) and len(base) and got.size else np.full(len(got), -1, np.int32))
        if hits_only:
            return out_h
        out = np.full(len(h.instance), -1, np.int32)
        out[got] = out_h
        return out

    def inherit(self, old: "Session"):
        """Carry the decision of the same scene's previous session (its plan, the structure
        later casts use, the online rule's totals) when the scene is about as large: a frame
        that moved something does not plan again."""
        if old is None or old.chosen is None:
            return
        n, m = self.layout.triangle_count, old.layout.triangle_count
        if not (m / 2 <= n <= 2 * m):
            return
        self.plan, self.chosen, self.calibration, self.kinds = old.plan, old.chosen, old.calibration, old.kinds
        self.grid_time, self.grid_rays = old.grid_time, old.grid_rays

    def adopt(self, other: "Session"):
        """Take the structure ``other`` chose for this scene when this session has not chosen
        (a sweep's session, not stored, hands its choice to the stored one the next frame
        inherits from, instead of every frame deciding again)."""
        if self.chosen is None and other.chosen is not None:
            self.chosen, self.calibration, self.kinds = other.chosen, other.calibration, other.kinds

    @property
    def triangle_normals(self) -> np.ndarray:
        """(T, 3) float32 unit normals, cross(v1 - v0, v2 - v0) / |...| in float64 (the
        orientation Blender's ``ray_cast`` reports: extraction keeps each polygon's winding)."""
        if self._normals is None:
            self._normals = unit_normals(self.mesh.tri_vertices)
        return self._normals

    def per_triangle(self):
        """(object index, instance index, polygon index, unit normal) per triangle, each
        with one more row for a miss (-1, -1, -1, NaN) so that a miss's triangle -1 picks it."""
        if self._per_triangle is None:
            mesh, inst = self.mesh, self.mesh.instances
            tail = np.array([-1], np.int32)
            self._per_triangle = (
                np.concatenate([inst.instance_object[mesh.instance_index], tail]),
                np.concatenate([mesh.instance_index, tail]),
                np.concatenate([mesh.polygon_index, tail]),
                np.concatenate([self.triangle_normals, np.full((1, 3), np.nan, np.float32)]),
            )
        return self._per_triangle

    def tables(self):
        """(objects, their names) as object arrays, so ``objects[object_index[hit]]`` works."""
        if self._tables is None:
            obs = self.layout.instances.objects
            objects, names = np.empty(len(obs), object), np.empty(len(obs), object)
            objects[:] = obs
            names[:] = [ob.name if ob is not None else "" for ob in obs]
            self._tables = objects, names
        return self._tables

    def material_tables(self):
        """(materials as an object array, per triangle the index into it with one more row,
        -1, for a miss), from the extraction's 'material' attribute (``get`` with it)."""
        if self._materials is None:
            inst = self.mesh.instances
            if inst.triangle_material is None:
                raise RuntimeError("the session was extracted without 'material'")
            mats = np.empty(len(inst.materials), object)
            mats[:] = inst.materials
            self._materials = mats, np.concatenate([inst.triangle_material, np.array([-1], np.int32)])
        return self._materials

    @property
    def fingerprint(self):
        return self.head, self.body

    def structure(self, kind: str, **config):
        """The structure ``kind`` over this session's mesh, built once per config."""
        k = (kind, tuple(sorted(config.items())))
        acc = self.structures.get(k)
        if acc is None:
            self.mesh.prepare()
            acc = self.structures[k] = core.build(self.mesh, kind, **config)
        return acc

    def query(self, o, d, tmin, tmax, *, any_hit=False, structure="auto", budget, kinds, calibration,
              samples, grid_config, flat=True, slot=None):
        """Nearest hits (``core.Hits``) or any-hit booleans of one batch, and the structure used.

        'grid', 'bvh', 'embree' use that structure.  'auto': the session's first query
        plans (``core.plan``, the paper's rule for ``budget`` rays, timing its samples
        from this batch and keeping their answers); the structure it picks serves every
        later query.  While that is the grid, a later query first applies the decision to
        the rays of all queries so far: switch when they pass the plan's break-even, or
        by the online rule (``core.ski_rental``) once the grid's accumulated trace time
        reaches the estimated build time of the candidate estimated fastest per ray.
        ``flat=False``: trace with the two-level scene (``tracer``; its hits are
        ``core.InstanceHits``, decoded by ``decode``) wherever the flat mesh is not needed
        (the first plan of a scene traces flat).  ``slot``: a sweep's session (``swept``)
        takes per ray its instant, and its hits name placement ``slot * I + i``.
        """
        if self.sweep is not None:
            if flat or slot is None:
                raise ValueError("a sweep's session traces on two levels, each ray with its instant (slot)")
            out, kind = self._query(o, d, tmin, tmax, any_hit, structure, budget, kinds, calibration, samples,
                                    grid_config, False, {"slot": slot})
            if not any_hit:
                got = out.instance >= 0
                out.instance[got] += (np.asarray(slot)[got] * len(self.sweep[0].placement_group)).astype(np.int32)
            return out, kind
        return self._query(o, d, tmin, tmax, any_hit, structure, budget, kinds, calibration, samples, grid_config,
                           flat, {})

    def _query(self, o, d, tmin, tmax, any_hit, structure, budget, kinds, calibration, samples, grid_config, flat,
               extra):
        # the structures of a changed scene serve this session's rays: this batch's, until the next change
        pick = self.structure if flat else (lambda kind, **c: self.tracer(kind, rays=len(o), batch=(o, d, tmin, tmax), **c))
        if structure != "auto":
            acc = pick("grid", **grid_config) if structure == "grid" else pick(structure)
            t0 = time.perf_counter()
            out = (acc.occluded if any_hit else acc.trace)(o, d, tmin, tmax, **extra)
            self.timings["trace"] += time.perf_counter() - t0
            return out, structure
        if self.chosen is None and not flat and (self.instanced or self.sweep is not None):
            self.calibration, self.kinds = calibration, tuple(k for k in kinds if k != "grid")
            fast = [k for k in ("embree", "bvh") if k in kinds]
            self.chosen = fast[0] if fast else "grid"
        if self.chosen is None:
            grid = self.cached("grid", **grid_config)
            p = core.plan(self.mesh, budget, calibration, rays=(o, d, tmin, tmax), samples=samples, grid=grid,
                          grid_config=grid_config, kinds=kinds)
            self.keep(p.grid, **grid_config)
            self.plan, self.calibration, self.kinds = p, calibration, tuple(k for k in kinds if k != "grid")
            self.chosen = p.chosen
            if p.chosen != "grid":
                p.structure = self.structure(p.chosen, **p.configs.get(p.chosen, {}))
            t0 = time.perf_counter()
            rest, rays = p.split(o, d, tmin, tmax)
            acc = p.accel()
            part = (acc.occluded if any_hit else acc.trace)(*rays)
            out = p.merge(len(o), rest, part)
            if p.chosen == "grid":
                self.grid_time += p.grid_sample_per_ray * p.workload_samples + time.perf_counter() - t0
                self.grid_rays += len(o)
            return out, p.chosen
        if self.chosen == "grid":
            self._maybe_switch(len(o))
        own = grid_config if self.chosen == "grid" else {}
        if flat:
            acc = self.structure(self.chosen, **own)
        else:  # each part by the rule over its life, the session's choice where none can be priced
            acc = self.tracer(self.chosen, rays=len(o), batch=(o, d, tmin, tmax), auto=True, grid_config=grid_config,
                              **own)
        t0 = time.perf_counter()
        out = (acc.occluded if any_hit else acc.trace)(o, d, tmin, tmax, **extra)
        dt = time.perf_counter() - t0
        self.timings["trace"] += dt
        if self.chosen == "grid":
            self.grid_time += dt
            self.grid_rays += len(o)
        if flat:
            return out, self.chosen
        key = self.auto_key(grid_config)
        self.served(key, len(o))
        parts = self.choices.get(key)
        # the structure that holds the most triangles names the trace (the parts are in ``describe``)
        return out, max(parts, key=lambda c: c["triangles"])["kind"] if parts else self.chosen

    def _maybe_switch(self, m: int):
        """Leave the grid for the candidate estimated fastest per ray, when the rays of all
        queries pass the plan's break-even or the online rule says so."""
        n = self.layout.triangle_count
        ests = [self.calibration.estimate(k, n) for k in self.kinds if k in self.calibration.fits]
        if not ests:
            return
        best = min(ests, key=lambda e: (e.per_ray, e.kind))
        p = self.plan
        if self.grid_rays + m > p.break_even and p.break_even_kind is not None:
            self.chosen = min(ests, key=lambda e: (e.build_time + (self.grid_rays + m) * e.per_ray, e.kind)).kind
        elif core.ski_rental(self.grid_time, self.grid_rays, best) == "switch":
            self.chosen = best.kind

    def cached(self, kind: str, **config):
        return self.structures.get((kind, tuple(sorted(config.items()))))

    def keep(self, acc, **config):
        """Adopt a structure built elsewhere over this mesh (a plan's grid)."""
        if acc is not None and getattr(acc, "mesh", None) is self.mesh:
            self.structures.setdefault((acc.kind, tuple(sorted(config.items()))), acc)


def _choice_dict(c: dict) -> dict:
    """A part's choice (``Session._life_choice``) as JSON: times in seconds, a break-even of
    null for never."""
    be = c.get("break_even")
    return {"what": c.get("what", ""), "kind": c["kind"], "triangles": c.get("triangles", 0),
            "rays_expected": float(c["rays"]), "life": c["life"], "why": c["why"],
            "built_already": list(c.get("built", ())),
            "totals": {k: float(v) for k, v in c.get("totals", {}).items()},
            "break_even": float(be) if be is not None and be != float("inf") else None,
            "break_even_kind": c.get("break_even_kind")}


def _settings(depsgraph, settings, selected_only, grid_density):
    props = settings if settings is not None else getattr(depsgraph.scene, "hybrid_raycast", None)
    if selected_only is None:
        selected_only = bool(props.selected_only) if props is not None else False
    if grid_density is None:
        grid_density = float(props.grid_density) if props is not None else None
    return bool(selected_only), grid_density


def session_key(depsgraph, selected_only: bool) -> tuple:
    return depsgraph.scene.as_pointer(), depsgraph.view_layer.as_pointer(), bool(selected_only)


def get(depsgraph, settings=None, *, selected_only=None, attributes=(), progress=None, strict=True) -> Session:
    """The session of ``depsgraph`` (evaluated; see ``evaluated``), extracting again
    unless the stored one has the same fingerprint.  ``settings``: a
    ``scene.hybrid_raycast`` (default the depsgraph scene's) for selected-only.
    ``attributes``: per-corner or per-triangle data the caller needs ('normal', 'uv',
    'material'), read once.
    Triangles with a NaN or infinite corner are left out (``Session.left_out`` says whose,
    and ``warnings.warn`` once per extraction); ``strict`` (the default, for the operators)
    raises InvalidGeometry naming them instead.  Nothing is stored when extraction fails."""
    check_depsgraph(depsgraph)
    selected_only, _ = _settings(depsgraph, settings, selected_only, None)
    head, body = fingerprint(depsgraph, selected_only)
    key = session_key(depsgraph, selected_only)
    want = frozenset(attributes)
    old = SESSIONS.get(key)
    if old is not None and old.head == head and old.body == body:
        if strict and old.layout.left_out:
            raise InvalidGeometry(_invalid_message(depsgraph))
        old.timings = dict.fromkeys(TIMING_KEYS, 0.0)
        if not want <= old.attributes:
            _add_attributes(old, depsgraph, selected_only, want | old.attributes)
        old._summary["frame"] = depsgraph.scene.frame_current
        return old
    t0 = time.perf_counter()
    layout, summary = extract_layout(depsgraph, selected_only=selected_only, progress=progress,
                                     attributes=tuple(want), cache=MESHES)
    if layout.left_out:
        if strict:
            raise InvalidGeometry(_invalid_message(depsgraph))
        warnings.warn(left_out_message(layout.left_out), RuntimeWarning, stacklevel=3)
    s = Session(key, head, body, layout, summary, want, changed=old is not None)
    if old is not None:
        s.still = _still(layout, old.layout)
    s.timings["extract"] = time.perf_counter() - t0
    s.inherit(old)
    SESSIONS[key] = s
    _prune()
    return s


def described(depsgraph, selected_only=None) -> dict | None:
    """``Session.describe`` of the stored session of ``depsgraph``'s scene and view layer as
    it is (no extraction; None without one)."""
    selected_only, _ = _settings(depsgraph, None, selected_only, None)
    s = SESSIONS.get(session_key(depsgraph, selected_only))
    return s.describe() if s is not None else None


def swept(base: Session, layout, matrices, still) -> Session:
    """A session for a sweep whose placements only move: ``layout`` (the base session's
    scene at the sweep's first instant) at K instants, ``matrices`` (K, I, 4, 4) world, each
    ray traced at its own instant (``query(..., slot=)``: ``core.Swept`` under the ``still``
    placements' kept flat structure).  Its ``layout`` is ``layout.tiled(matrices)``, so a hit
    names placement ``k * I + i`` (placement i at instant k) and decodes with that instant's
    matrix.  It shares the base's meshes, bottoms and decision; it is not stored."""
    m = np.asarray(matrices, np.float64)
    s = Session(base.key, base.head, base.body, layout.tiled(m), base._summary, base.attributes, changed=True)
    s.sweep = (layout, m)
    s.still = np.asarray(still, bool)
    s.inherit(base)
    return s


def _placement_ids(layout) -> list:
    return [(layout.groups[g].key, m.tobytes()) for g, m in zip(layout.placement_group.tolist(), layout.matrices)]


def _still(layout, before) -> np.ndarray:
    """(I,) bool: the placements ``before`` had as well (the same mesh key and matrix)."""
    seen = set(_placement_ids(before))
    return np.array([p in seen and p[0] is not None for p in _placement_ids(layout)], bool)


def _prune():
    """Forget the meshes no live session uses (an animated mesh is a new one every frame)."""
    live = {g.key for s in SESSIONS.values() for g in s.layout.groups if g.key is not None}
    for k in [k for k in MESHES if k not in live]:
        del MESHES[k]
    for k in [k for k in BOTTOMS if k[0] not in live]:
        del BOTTOMS[k]
    soups = {k[2] for k in SOUPS}
    for k in [k for k in LIFE if k[1] not in (live if k[0] == "bottom" else soups)]:
        del LIFE[k]


def _add_attributes(s: Session, depsgraph, selected_only, attributes):
    """Read the scene again with more per-corner or per-triangle data; the geometry (and so
    every structure built) stays, the new layout replaces the old one."""
    layout, _ = extract_layout(depsgraph, selected_only=selected_only, attributes=tuple(attributes), cache=MESHES)
    old = s.layout
    if layout.triangle_count != old.triangle_count or not np.array_equal(layout.tri_base, old.tri_base) \
            or not np.array_equal(layout.placement_group, old.placement_group):
        raise RuntimeError("the scene extracted differently with the same fingerprint")  # extraction is deterministic
    if old._flat is not None:  # structures over the flat mesh keep it: give it the new arrays
        mesh = layout.flat()
        if not np.array_equal(mesh.triangles, old._flat.triangles) or not np.array_equal(mesh.vertices,
                                                                                          old._flat.vertices):
            raise RuntimeError("the scene extracted differently with the same fingerprint")
        for name in ("corner_normals", "corner_uvs", "materials", "triangle_material"):
            setattr(old._flat.instances, name, getattr(mesh.instances, name))
        layout._flat = old._flat
    s.layout = layout
    s._materials = None
    s.attributes = frozenset(attributes)
    _prune()


def evaluated(scene=None, view_layer=None):
    """The evaluated depsgraph of ``scene`` and ``view_layer`` (default: the context's)."""
    ctx = bpy.context
    if scene is None or (scene == ctx.scene and (view_layer is None or view_layer == ctx.view_layer)):
        return ctx.evaluated_depsgraph_get()
    vl = view_layer if view_layer is not None else scene.view_layers[0]
    dg = vl.depsgraph
    dg.update()
    return dg


# -- the sidebar's stale flag ------------------------------------------------------------------

def remember_analysis(depsgraph, selected_only: bool, body):
    ANALYSED[depsgraph.scene.as_pointer()] = (depsgraph.view_layer.as_pointer(), bool(selected_only), body)


def adopt_own_write(scene, view_layer, before):
    """After the add-on wrote into the scene (the AO bake's colour attribute): evaluate
    and take the new fingerprint as current for whatever matched ``before`` (head, body)."""
    global _adopting
    _adopting = True
    try:
        depsgraph = evaluated(scene, view_layer)
    finally:
        _adopting = False
    scene_ptr = depsgraph.scene.as_pointer()
    for s in SESSIONS.values():
        if s.key[0] == scene_ptr and (s.head, s.body) == before:
            s.head, s.body = fingerprint(depsgraph, s.key[2])
    seen = ANALYSED.get(scene_ptr)
    if seen is not None and seen[0] == depsgraph.view_layer.as_pointer() and seen[2] == before[1]:
        ANALYSED[scene_ptr] = (seen[0], seen[1], fingerprint(depsgraph, seen[1])[1])


#: original object pointer -> geometry updates seen.  Blender 5.0 gives an evaluated mesh a
#: new session_uid on every re-evaluation, but bpy 5.3 updates the evaluated copy of a mesh
#: without modifiers in place (same session_uid) after an edit of its data (a vertex moved,
#: a UV map added; tests/test_api_session.py and test_operators.py on the matrix's bpy-5.3
#: leg), so the fingerprint also counts the geometry updates the depsgraph reports.
EDITS: dict[int, int] = {}


def _count_edits(depsgraph):
    for u in depsgraph.updates:
        idb = u.id
        if isinstance(idb, _OBJECT) and u.is_updated_geometry:
            k = idb.original.as_pointer()
            EDITS[k] = EDITS.get(k, 0) + 1


@persistent
def on_depsgraph_update(scene, depsgraph):
    _count_edits(depsgraph)
    if _adopting:
        return
    seen = ANALYSED.get(scene.as_pointer())
    props = getattr(scene, "hybrid_raycast", None)
    if seen is None or props is None or not props.has_results or props.geometry_changed:
        return
    if depsgraph.view_layer.as_pointer() != seen[0]:
        return
    if fingerprint(depsgraph, seen[1])[1] != seen[2]:
        props.geometry_changed = True


@persistent
def on_load_post(*_args):
    clear()


@contextlib.contextmanager
def expecting(calls: int):
    """Within it, a job has said how many calls it makes: the parts that last (the still
    soup, the bottom levels) are chosen for that many calls of the current one's rays
    (``Session._life_choice``), not by the ski-rental rule.  Set ``JOB[0]`` to the calls
    still to come before each one when they count down."""
    before = JOB[0]
    JOB[0] = max(1, int(calls))
    try:
        yield JOB
    finally:
        JOB[0] = before


def clear():
    SESSIONS.clear()
    MESHES.clear()
    BOTTOMS.clear()
    SOUPS.clear()
    LIFE.clear()
    settings.PARTS.clear()
    settings.POINTS.clear()
    forget()
    ANALYSED.clear()
    EDITS.clear()


_HANDLERS = (
    ("depsgraph_update_post", on_depsgraph_update),
    ("frame_change_post", on_depsgraph_update),
    ("load_post", on_load_post),
)


def register():
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)


def unregister():
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        # match by name too: a reloaded module brings new function objects
        for h in [h for h in lst if h is fn or (getattr(h, "__name__", "") == fn.__name__
                                               and getattr(h, "__module__", "") == fn.__module__)]:
            lst.remove(h)
    clear()
