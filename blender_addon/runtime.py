"""Per-session caches behind the preview objects, rebuilt lazily from stored file paths.

Nothing here is saved: the .blend holds the attributes and properties, this module holds
the decoded avatar and the evaluators (rebuilt after a file load, on first use).
"""

import os

import bpy
import numpy as np

from ..core.bridge.budget import load_avatar
from ..core.bridge.splats import preview_order, splat_evaluator
from ..core.io.safe_io import file_digest
from . import depth, preview


def mesh_faces(me):
    """Triangle vertex indices [F,3] (quads and n-gons cannot be an avatar's template)."""
    totals = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_total", totals)
    if len(totals) and (totals != 3).any():
        raise ValueError(f"{me.name} has non-triangle faces; avatars bind to triangle templates")
    idx = np.empty(len(me.loops), np.int32)
    me.loops.foreach_get("vertex_index", idx)
    return idx.reshape(-1, 3)


class _Entry:
    def __init__(self, path, loaded=None, template_faces=None):
        self.path = path
        self.avatar, self.budget = loaded or load_avatar(path, template_faces)
        self.weights = self.avatar.forest.weights()
        self.order = preview_order(self.avatar)  # face of each preview point
        self.point_of_face = np.argsort(self.order)
        self.face_at = self.avatar.forest.stream_order()  # face of each stream position
        self.evaluator = None  # the Gaussians of the last count a frame change showed
        self.full = None  # every Gaussian's: what a budget raised past the placed points evaluates
        self.placed = None  # the evaluator whose outputs hold the placed points
        self.n_vertices = int(self.avatar.forest.template_faces.max()) + 1
        self.valid = 0  # preview points (by stream rank) placed on the vertices of frame_key
        self.frame_key = None  # the mesh vertices the placed points were evaluated on
        self.depth_failed = False  # its depth could not be written on the mesh (Edit Mode): retried

    def evaluator_for(self, count):
        if count >= self.avatar.num_gaussians:
            if self.full is None:
                self.full = splat_evaluator(self.avatar, None, self.weights, self.order)
            return self.full
        if self.evaluator is None or self.evaluator.n != count:
            self.evaluator = splat_evaluator(self.avatar, count, self.weights, self.order)
        return self.evaluator


_cache: dict = {}


def file_signature(path) -> str:
    """Size and hash of a file: what the preview's saved attributes were made from."""
    return f"{os.path.getsize(path)}:{file_digest(path)}"


def resolve(path, library=None) -> str:
    return os.path.normpath(bpy.path.abspath(path, library=library)) if path else ""


def path_library(obj):
    """The library an object's "//" paths are relative to: its own when it is linked, its
    reference's when it is a library override, None (the open file) when it is local."""
    if obj.library is not None:
        return obj.library
    ov = obj.override_library
    ref = ov.reference if ov is not None else None
    return ref.library if ref is not None else None


def avatar_path(obj) -> str:
    """The preview's avatar file. Blender rebases its own relative paths when data is appended
    or made local from a .blend in another folder, but not an add-on's: the stored "//" path is
    then relative to that file, and the absolute path stored beside it still finds the avatar."""
    state = obj.pa_avatar
    path = resolve(state.filepath, path_library(obj))
    fallback = state.filepath_absolute
    if path and not os.path.isfile(path) and fallback and os.path.isfile(fallback):
        return os.path.normpath(fallback)
    return path


def entry(obj):
    """The cache entry of a preview object, loading its avatar file if needed (or None)."""
    if obj.get("pa_splat_ply"):  # static PLY splats (ply_import): nothing to evaluate
        return None
    state = obj.pa_avatar
    path = avatar_path(obj)
    key = obj.session_uid
    e = _cache.get(key)
    if e is not None and e.path == path:
        return e
    if not path or not os.path.isfile(path):
        state.status = f"Avatar file not found: {path}" if path else "No avatar file"
        return None
    src = state.source
    try:  # the mesh stands in for a template the stream does not embed
        faces = mesh_faces(src.data) if src is not None and src.type == "MESH" else None
    except ValueError:
        faces = None
    _drop_dead()
    try:
        # The preview's ranks, colours and opacities are saved in the .blend from the file it was
        # loaded from: another file at that path (a re-export, a retrained run) would be mixed
        # with them point by point.
        if state.file_signature and file_signature(path) != state.file_signature:
            state.status = f"{path} changed since this preview was loaded: load the avatar again (Load Avatar)"
            state.count = 0
            preview.set_count(obj, 0)
            return None
        e = _cache[key] = _Entry(path, template_faces=faces)
    except (ValueError, OSError) as exc:
        state.status = f"Cannot read the avatar: {exc}"
        return None
    return e


def cached(obj):
    """The preview's cache entry if it has one, loading nothing (for handlers that only look)."""
    return _cache.get(obj.session_uid)


def prime(obj, path, avatar, budget):
    """Cache an avatar the caller has just read, so it is not decoded twice."""
    _drop_dead()
    _cache[obj.session_uid] = _Entry(resolve(path), (avatar, budget))


def _drop_dead():
    """Forget the decoded avatars of previews that no longer exist (deleted by the user): each
    holds the whole avatar and its evaluator."""
    live = {o.session_uid for o in bpy.data.objects}
    for key in [k for k in _cache if k not in live]:
        del _cache[key]


def forget(obj=None):
    if obj is None:
        _cache.clear()
    else:
        _cache.pop(obj.session_uid, None)


def invalidate():
    """Keep decoded avatars but treat every preview point as needing evaluation."""
    for e in _cache.values():
        e.valid, e.frame_key = 0, None


def previews(scene):
    return [o for o in scene.objects if o.pa_avatar.is_preview and o.type == "MESH"]


def bound_mesh(obj):
    """The mesh the preview ``obj`` is bound to, or None once it is deleted. Delete in the 3D
    View only unlinks it from its collections while the preview's pointer to it (a user) keeps
    it in the file's data: shown and evaluated by no scene, it is no mesh to follow."""
    src = obj.pa_avatar.source
    return src if src is not None and src.users_collection else None


def bound_previews(mesh):
    """The previews bound to ``mesh``, parented to it or not: Clear Parent leaves a preview
    bound and drawing, so its mesh's panel, Load Avatar and depth colours still find it."""
    # A preview's pointer is a user of its mesh: a mesh used by its collections alone has none,
    # and the panels ask this of every selected mesh at each redraw (a scan of every object).
    if mesh is None or mesh.users <= len(mesh.users_collection):
        return []
    return [o for o in bpy.data.objects if o.pa_avatar.is_preview and o.pa_avatar.source == mesh]


def source_vertices(source, depsgraph):
    """Evaluated vertices of the bound mesh (shape keys, armatures, sculpt all applied)."""
    src_eval = source.evaluated_get(depsgraph)
    me = src_eval.data
    out = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", out)
    return out.reshape(-1, 3)


# Modifiers that can change a mesh's vertex or face count while the evaluated mesh does not
# show it (GPU subdivision draws the last Subdivision Surface without evaluating it on the CPU).
_SUBDIVIDERS = {"SUBSURF", "MULTIRES"}


def _modifier_names(source, depsgraph, types=None):
    render = getattr(depsgraph, "mode", "VIEWPORT") == "RENDER"
    out = []
    for m in source.modifiers:
        on = m.show_render if render else m.show_viewport
        if on and (types is None or m.type in types):
            if m.type in _SUBDIVIDERS and getattr(m, "render_levels" if render else "levels", 1) == 0:
                continue  # subdivides nothing in this mode
            out.append(f"{m.type.replace('_', ' ').title()} '{m.name}'")
    return out


def topology_problem(obj, depsgraph):
    """Why the bound mesh's evaluated topology is not the one the avatar was bound to
    (Remesh, Subdivision Surface, Decimate, ...), or "" when it is."""
    state, src = obj.pa_avatar, obj.pa_avatar.source
    tv, tf = state.template_vertices, state.template_faces
    if not tv:  # bound before the counts were recorded
        return ""
    me = src.evaluated_get(depsgraph).data
    nv, nf = len(me.vertices), len(me.polygons)
    if (nv, nf) != (tv, tf):
        if src.data.is_editmode:  # its evaluated mesh is the edit mesh's, not one modifiers made
            return f"{src.name} is in Edit Mode: its Gaussians show again once you leave it"
        mods = _modifier_names(src, depsgraph)
        by = f" (modifiers: {', '.join(mods)})" if mods else ""
        return (
            f"{src.name} evaluates to {nv} vertices / {nf} faces{by}, the avatar is bound to its "
            f"{tv} / {tf}: Gaussians would sit on unrelated vertices. Disable the modifiers that change "
            f"the topology, or set Follow to 'Shape keys only'"
        )
    subdiv = _modifier_names(src, depsgraph, _SUBDIVIDERS)
    if subdiv:
        return (
            f"{src.name} has {', '.join(subdiv)}: it moves the surface off the vertices the avatar is "
            f"bound to. Disable it, or set Follow to 'Shape keys only'"
        )
    return ""


def shape_key_vertices(source, depsgraph):
    """The mesh's own vertices with its relative shape keys mixed at their current (evaluated)
    values, before any modifier: one pass per active key, none per vertex."""
    me = source.data
    co = np.empty(len(me.vertices) * 3, np.float32)
    key = me.shape_keys
    if key is None:
        me.vertices.foreach_get("co", co)
        return co.reshape(-1, 3), ""
    if not key.use_relative:
        return None, f"{source.name}: absolute shape keys cannot be followed without modifiers"
    key_eval = key.evaluated_get(depsgraph)
    blocks = key.key_blocks
    cache = {}

    def block_co(kb):
        if kb.name not in cache:
            a = np.empty(len(me.vertices) * 3, np.float32)
            kb.data.foreach_get("co", a)
            cache[kb.name] = a
        return cache[kb.name]

    out = block_co(key.reference_key).astype(np.float64)
    for kb, kb_eval in zip(blocks[1:], key_eval.key_blocks[1:]):
        value = kb_eval.value
        if kb.mute or value == 0.0:
            continue
        if kb.vertex_group:
            return None, f"{source.name}: shape key '{kb.name}' is limited to a vertex group; follow the evaluated mesh"
        out += value * (block_co(kb) - block_co(kb.relative_key))
    return out.astype(np.float32).reshape(-1, 3), ""


def own_mesh(obj):
    """The preview's mesh, made its own first if another preview shares it (Alt+D, obj.copy())
    or it is linked from a library (a library override's mesh: Blender drops writes to linked
    data). Each preview writes every point of its mesh for its own budget, frame and bound
    mesh: on a shared mesh the last writer's points would show in both."""
    me = obj.data
    shared = me.users > 1 and any(o != obj and o.data == me and o.pa_avatar.is_preview for o in bpy.data.objects)
    if shared or me.library is not None:
        obj.data = me = me.copy()
    return me


def refresh(obj, depsgraph, count=None, upto=None):
    """Show the first ``count`` Gaussians placed on the mesh's current evaluated shape,
    evaluating (positions, rotations, scales) the first ``upto`` (default ``count``) unless
    they already sit on these very vertices. Returns False (and sets status) when it cannot."""
    state = obj.pa_avatar
    e = entry(obj)
    src = bound_mesh(obj)
    if e is None or src is None or src.type != "MESH":
        if src is None:
            state.status = "No mesh bound"
        if e is not None:  # show only what was placed on the mesh before it went, never unplaced points
            preview.set_count(obj, min(e.budget.count_for_slider(state.budget) if count is None else count, e.valid))
        return False
    count = e.budget.count_for_slider(state.budget) if count is None else count
    if state.bind_mode == "SHAPE_KEYS":
        verts, problem = shape_key_vertices(src, depsgraph)
    else:
        problem = topology_problem(obj, depsgraph)
        verts = None if problem else source_vertices(src, depsgraph)
    if not problem and len(verts) < e.n_vertices:
        problem = f"{src.name} has {len(verts)} vertices; the avatar needs {e.n_vertices}"
    if problem:
        # Never leave Gaussians standing where they were: hide them until the mesh fits again.
        state.status = problem
        preview.set_count(obj, 0)
        e.valid = 0
        return False
    if obj.data.is_editmode:  # its points live in the edit mesh then, which has no attributes to write
        state.status = f"{obj.name} is in Edit Mode: its Gaussians follow the mesh again once you leave it"
        preview.set_count(obj, min(count, e.valid))  # never points it has not placed
        # Leaving Edit Mode writes the edit mesh's points back as they were: placed anew then
        # (handlers.on_depsgraph_update), whichever frame it left on.
        e.frame_key = None
        return False
    if obj.library is not None:  # its points are the library's, saved at another frame
        state.status = (
            f"{obj.name} is linked from {obj.library.name}: its Gaussians cannot follow {src.name} here. "
            "Make it local (Object > Relations > Make Local > Selected Objects and Data) or add a library "
            "override (Object > Library Override > Make)"
        )
        preview.set_count(obj, 0)
        e.valid = 0
        return False
    me = obj.data
    if len(me.vertices) != e.avatar.num_gaussians:  # hidden, not left standing where they were
        state.status = "Preview point count does not match the avatar file: reload the avatar"
        preview.set_count(obj, 0)
        e.valid = 0
        return False
    preview.set_count(obj, count)
    # Points already placed on these very vertices stay: a budget step writes the mesh's depth
    # attribute, which re-evaluates the mesh and calls here again, and must not re-bind (and
    # rewrite) every Gaussian for a frame that did not move.
    if e.valid < count or e.frame_key is None or not np.array_equal(verts, e.frame_key):
        me = own_mesh(obj)
        ev = e.evaluator_for(max(count, upto or 0))
        means, quats, scales = ev(verts)
        me.attributes["position"].data.foreach_set("vector", means.ravel())
        me.attributes["rotation"].data.foreach_set("value", quats.ravel())
        me.attributes["scale"].data.foreach_set("vector", scales.ravel())
        me.update()
        e.valid, e.placed, e.frame_key = ev.n, ev, verts
    apart = placement_problem(obj, src, depsgraph)
    if state.status != apart:
        state.status = apart
    return True


def placement_problem(obj, src, depsgraph):
    """Why the preview draws its Gaussians away from its mesh, or "". They are placed in the
    mesh's space and drawn in the preview's, one space while it is parented to the mesh and
    untransformed; Apply Scale/Rotation on the mesh (Blender keeps children where they were by
    giving them the transform applied), re-parenting or moving the preview tell them apart."""
    here = np.array(obj.evaluated_get(depsgraph).matrix_world)
    there = np.array(src.evaluated_get(depsgraph).matrix_world)
    return "" if np.allclose(here, there, rtol=1e-5, atol=1e-6) else _apart(obj, src)


def _apart(obj, src):
    return (
        f"{obj.name} is not where {src.name} is (its own transform or parent): its Gaussians are drawn away from "
        f"the mesh. To put them back, parent it to {src.name} without inverse (Object > Parent) and clear its "
        "transform (Object > Clear > All)"
    )


def placement_status(obj, depsgraph):
    """After the preview moved: say whether it still draws its Gaussians on its mesh, placing
    nothing (another problem's status stands)."""
    state, src = obj.pa_avatar, obj.pa_avatar.source
    if state.status in ("", _apart(obj, src)):
        problem = placement_problem(obj, src, depsgraph)
        if state.status != problem:
            state.status = problem


def apply_budget(obj, context=None, depsgraph=None):
    """Budget slider → modifier Count input (+ readouts). Points past what the last frame
    evaluation covered are evaluated only when the budget grows beyond it."""
    state = obj.pa_avatar
    if not state.is_preview:
        return
    e = entry(obj)
    if e is None:
        return
    b = e.budget
    count = b.count_for_slider(state.budget)
    state.count = count
    state.total = b.total
    state.megabytes = b.bytes_for_count(count) / 1e6
    state.level_reached = b.level_reached(count)
    preview.set_count(obj, count)
    if count > e.valid:  # every Gaussian, so that scrubbing on at this frame evaluates nothing more
        context = context or bpy.context
        refresh(obj, depsgraph or context.evaluated_depsgraph_get(), count, upto=b.total)
    write_depth(obj, e, count)


def write_depth(obj, e, count):
    """The mesh's depth (and its colours) for what the budget shows, ``count`` Gaussians of the
    preview ``obj`` (cache entry ``e``), when the mesh's depth describes it (or none: the first
    moved takes it); a linked preview's status says why it shows nothing."""
    src = bound_mesh(obj)
    if src is not None and src.type == "MESH" and obj.library is None and depth.depth_owner(src) in (None, obj):
        try:
            depth.apply_depth(src, e.avatar.forest, count, e.budget.max_depth(e.avatar.forest), obj)
            e.depth_failed = False
        except ValueError as exc:  # the mesh was edited to another face count, or is in Edit Mode
            obj.pa_avatar.status = f"Depth not shown: {exc}"
            e.depth_failed = True
