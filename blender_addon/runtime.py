"""Per-session caches behind the preview objects, rebuilt lazily from stored file paths.

Nothing here is saved: the .blend holds the attributes and properties, this module holds
the decoded avatar and the evaluators (rebuilt after a file load, on first use).
"""

import os

import bpy
import numpy as np

from ..core import preview_data
from . import preview


class _Entry:
    def __init__(self, path, loaded=None):
        self.path = path
        self.avatar, self.budget = loaded or preview_data.load_avatar(path)
        self.weights = self.avatar.forest.weights()
        self.order = preview_data.preview_order(self.avatar)  # stream rank of each preview point
        self.point_of_rank = np.argsort(self.order)
        self.evaluator = None
        self.n_vertices = int(self.avatar.forest.template_faces.max()) + 1
        self.valid = 0  # preview points whose positions match the last evaluated frame
        self.frame_key = None

    def evaluator_for(self, count):
        if self.evaluator is None or self.evaluator.n != count:
            self.evaluator = preview_data.splat_evaluator(self.avatar, count, self.weights, self.order)
        return self.evaluator


_cache: dict = {}


def resolve(path) -> str:
    return os.path.normpath(bpy.path.abspath(path)) if path else ""


def entry(obj):
    """The cache entry of a preview object, loading its avatar file if needed (or None)."""
    if obj.get("pa_splat_ply"):  # static PLY splats (ply_import): nothing to evaluate
        return None
    state = obj.pa_avatar
    path = resolve(state.filepath)
    key = obj.session_uid
    e = _cache.get(key)
    if e is not None and e.path == path:
        return e
    if not path or not os.path.isfile(path):
        state.status = f"Avatar file not found: {path}" if path else "No avatar file"
        return None
    e = _cache[key] = _Entry(path)
    return e


def prime(obj, path, avatar, budget):
    """Cache an avatar the caller has just read, so it is not decoded twice."""
    _cache[obj.session_uid] = _Entry(resolve(path), (avatar, budget))


def forget(obj=None):
    if obj is None:
        _cache.clear()
    else:
        _cache.pop(obj.session_uid, None)


def invalidate():
    """Keep decoded avatars but treat every preview point as needing evaluation."""
    for e in _cache.values():
        e.valid = 0


def previews(scene):
    return [o for o in scene.objects if o.pa_avatar.is_preview and o.type == "MESH"]


def source_vertices(source, depsgraph):
    """Evaluated vertices of the bound mesh (shape keys, armatures, sculpt all applied)."""
    src_eval = source.evaluated_get(depsgraph)
    me = src_eval.data
    out = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", out)
    return out.reshape(-1, 3)


def refresh(obj, depsgraph, count=None):
    """Re-evaluate the first ``count`` Gaussians on the mesh's current evaluated shape and
    write positions, rotations and scales. Returns False (and sets status) when it cannot."""
    state = obj.pa_avatar
    e = entry(obj)
    src = state.source
    if e is None or src is None or src.type != "MESH":
        if src is None:
            state.status = "No mesh bound"
        return False
    count = e.budget.count_for_percent(state.budget) if count is None else count
    verts = source_vertices(src, depsgraph)
    if len(verts) < e.n_vertices:
        state.status = f"{src.name} has {len(verts)} vertices; the avatar needs {e.n_vertices}"
        return False
    means, quats, scales = e.evaluator_for(count)(verts)
    me = obj.data
    if len(me.vertices) != e.avatar.num_gaussians:
        state.status = "Preview point count does not match the avatar file: reload the avatar"
        return False
    me.attributes["position"].data.foreach_set("vector", means.ravel())
    me.attributes["rotation"].data.foreach_set("value", quats.ravel())
    me.attributes["scale"].data.foreach_set("vector", scales.ravel())
    me.update()
    e.valid = count
    if state.status:
        state.status = ""
    return True


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
    count = b.count_for_percent(state.budget)
    state.count = count
    state.total = b.total
    state.megabytes = b.bytes_for_count(count) / 1e6
    state.level_reached = b.level_reached(count)
    preview.set_count(obj, count)
    if count > e.valid:
        context = context or bpy.context
        refresh(obj, depsgraph or context.evaluated_depsgraph_get(), count)
