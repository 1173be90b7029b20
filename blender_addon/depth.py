"""Inspecting the hierarchy on the mesh: per-face subdivision depth (an int face attribute and
a legend stored on the object), depth colours as a toggle that puts the user's colour and
shading back, and a "show level k only" filter on the preview.

Depth is taken over the Gaussians the preview shows (the budget's count): faces none of whose
Gaussians has arrived (a stream cut inside the template level, a budget below it) get depth
NOT_ARRIVED and their own legend colour.
"""

import json

import bpy
import numpy as np

from ..core.bridge.depth import depth_colors, depth_legend, depth_per_face, per_corner

DEPTH_ATTR = "pa_depth"
COLOR_ATTR = "pa_depth_color"
LEVEL_MODIFIER = "PA Level"
LEVEL_GROUP = "PA Level Filter"


def require_writable(obj):
    """Raise ValueError naming ``obj`` when its mesh's attributes or its depth legend cannot be
    written: in Edit Mode (the edit mesh then holds the attributes, and theirs have no rows to
    read or write), or linked from a library (a library override included)."""
    if obj.type == "MESH" and obj.data.is_editmode:
        raise ValueError(f"{obj.name}: leave Edit Mode first")
    if obj.library or obj.override_library or (obj.data is not None and obj.data.library):
        raise ValueError(
            f"{obj.name} comes from a linked library: Blender keeps its mesh as the library has it. "
            "Make it local (Object > Relations > Make Local > Selected Objects and Data)"
        )


def depth_owner(obj):
    """The preview whose depth the mesh ``obj`` shows (attribute, legend, colours), or None
    when none is recorded or it is no longer a preview bound to ``obj`` (deleted, rebound).
    A mesh has one set of face colours: two previews bound to it (two avatars, Alt+D) at two
    budgets would otherwise overwrite each other's depth at each budget move. (Renamed, it is
    no longer recorded: the next budget moved takes the depth over.)"""
    pv = bpy.data.objects.get(obj.pa_mesh.depth_preview)
    return pv if pv is not None and pv.pa_avatar.is_preview and pv.pa_avatar.source == obj else None


def apply_depth(obj, forest, count=None, max_level=None, preview=None):
    """Write the depth of each face of ``obj`` over the first ``count`` Gaussians (all if
    None): the attribute, the legend and, while they are shown, the colours; ``preview``, the
    preview they are of, becomes the mesh's depth_owner. ``max_level``: the whole avatar's
    deepest subdivision depth below the template (the colour scale; default the forest's).
    Raises ValueError naming ``obj`` before changing anything when it cannot."""
    require_writable(obj)
    me = obj.data
    top = forest.max_depth if max_level is None else max(int(max_level), forest.max_depth)
    try:
        depth = depth_per_face(forest, len(me.polygons), count)
    except ValueError as exc:
        raise ValueError(f"{obj.name}: {exc}") from None
    attr = me.attributes.get(DEPTH_ATTR)
    if attr is not None and (attr.domain != "FACE" or attr.data_type != "INT"):
        me.attributes.remove(attr)
        attr = None
    changed = attr is None
    if attr is None:
        attr = me.attributes.new(DEPTH_ATTR, "INT", "FACE")
    else:
        old = np.empty(len(depth), np.int32)
        attr.data.foreach_get("value", old)
        changed = not np.array_equal(old, depth)
    # Written only when it changes: a write tags the mesh, which then re-evaluates (every shape
    # key, the armature) at each step of the budget slider.
    if changed:
        attr.data.foreach_set("value", depth)
    state = obj.pa_mesh
    if preview is not None and state.depth_preview != preview.name:
        state.depth_preview = preview.name
    changed |= state.depth_max_level != top  # the colour scale
    state.depth_max_level = top
    legend = state.depth_legend
    legend.clear()
    for d, n, rgb in depth_legend(depth, top):
        item = legend.add()
        item.depth, item.faces, item.color = d, n, rgb
    if state.depth_shown and (changed or me.color_attributes.get(COLOR_ATTR) is None):
        _write_colors(me, depth, top)
        me.update()  # redraw; otherwise no tag: a slider move must not re-evaluate the mesh
    return depth


def _write_colors(me, depth, max_level):
    attr = me.color_attributes.get(COLOR_ATTR)
    if attr is None:
        attr = me.color_attributes.new(COLOR_ATTR, "FLOAT_COLOR", "CORNER")
    totals = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_total", totals)
    colors = per_corner(depth_colors(depth, max_level), totals)
    attr.data.foreach_set("color", np.ascontiguousarray(colors, np.float32).ravel())
    me.color_attributes.active_color = attr


def _view_spaces(context):
    """(key, space) of every 3D view of every screen (windowless sessions included)."""
    for screen in bpy.data.screens:
        for ai, area in enumerate(screen.areas):
            for si, space in enumerate(area.spaces):
                if space.type == "VIEW_3D":
                    yield f"{screen.name}|{ai}|{si}", space


# The 3D views' colour mode is UI data: undo does not take it back, while it takes back the
# mesh's depth_shown and depth_saved. What the views showed before depth colours went on is
# kept here too (by the mesh's session id), where undo leaves it, and sync_views puts the views
# in step with the toggles an undo, a redo or a file load left.
_views_before = {}


def _set_views(color_type):
    for _key, sp in _view_spaces(None):
        sp.shading.color_type = color_type


def _put_back(shading):
    """The views' saved colour modes, where they still show depth colours (Attribute)."""
    for key, sp in _view_spaces(None):
        if key in shading and sp.shading.color_type == "VERTEX":
            sp.shading.color_type = shading[key]


def sync_views():
    """After undo/redo: views follow the meshes' depth toggles. A toggle undone puts back the
    colour modes its mesh's depth colours replaced; one redone shows them again."""
    shown = {o.session_uid: o for o in bpy.data.objects if o.type == "MESH" and o.pa_mesh.depth_shown}
    for key in reversed(list(_views_before)):  # the earliest saved modes are put back last
        if key not in shown:
            _put_back(_views_before.pop(key))
    for key, obj in shown.items():
        if key not in _views_before:
            try:
                saved = json.loads(obj.pa_mesh.depth_saved or "{}").get("shading", {})
            except (ValueError, AttributeError):
                saved = {}
            saved = saved if isinstance(saved, dict) else {}
            # What the views show now is what depth colours replace; where they show them
            # already (a file's own UI), what the mesh saved. (A file opened without its UI
            # has other views than it saved.)
            _views_before[key] = {
                k: saved.get(k, mode) if mode == "VERTEX" else mode
                for k, mode in ((k, sp.shading.color_type) for k, sp in _view_spaces(None))
            }
            _set_views("VERTEX")


def after_load():
    """A loaded file: the records were the previous file's; its own toggles decide."""
    _views_before.clear()
    sync_views()


def show_colors(context, obj, forest, count=None, max_level=None, preview=None):
    """Depth colours on: remember the mesh's active/render colours and every 3D view's colour
    mode, then show the depth colours of the first ``count`` Gaussians (of ``preview``) there
    (Solid mode, Attribute colour). Already on, they show ``preview``'s depth instead."""
    state, me = obj.pa_mesh, obj.data
    was_shown = state.depth_shown
    if not was_shown:
        ca = me.color_attributes
        saved = json.dumps(
            {
                "active": ca.active_color_name or "",
                "default": getattr(ca, "default_color_name", "") or "",
                "shading": {key: sp.shading.color_type for key, sp in _view_spaces(context)},
            }
        )
    # The depth first: when it cannot be computed (an edited mesh), the toggle and the saved
    # colours and shading must stay as they were.
    depth = apply_depth(obj, forest, count, max_level, preview)
    if not was_shown:
        state.depth_saved = saved
        state.depth_shown = True
        _views_before[obj.session_uid] = json.loads(saved)["shading"]
        _write_colors(me, depth, state.depth_max_level)
        me.update()
    for _key, sp in _view_spaces(context):
        sp.shading.color_type = "VERTEX"


def hide_colors(context, obj):
    """Depth colours off: remove them and put back what show_colors remembered."""
    state, me = obj.pa_mesh, obj.data
    saved = json.loads(state.depth_saved or "{}")
    ca = me.color_attributes
    attr = ca.get(COLOR_ATTR)
    if attr is not None:
        ca.remove(attr)
    for key in ("active", "default"):
        name = saved.get(key, "")
        if name and name in ca:
            if key == "active":
                ca.active_color = ca[name]
            elif hasattr(ca, "default_color_name"):
                ca.default_color_name = name
    # This session's record first: after a file load it names the views there are now.
    shading = _views_before.pop(obj.session_uid, None) or saved.get("shading", {})
    for key, sp in _view_spaces(context):
        if key in shading:
            sp.shading.color_type = shading[key]
    state.depth_shown = False
    state.depth_saved = ""
    me.update()


# -- "show level k only" -------------------------------------------------------------------
LEVEL_GROUP_VERSION = 2  # 2: a level shown alone keeps its coarse stand-ins (retire cleared)


def _level_group():
    ng = bpy.data.node_groups.get(LEVEL_GROUP)
    if ng is not None and ng.get("pa_version") == LEVEL_GROUP_VERSION:
        return ng
    ng = ng or bpy.data.node_groups.new(LEVEL_GROUP, "GeometryNodeTree")
    ng["pa_version"] = LEVEL_GROUP_VERSION
    ng.nodes.clear()
    ng.interface.clear()
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    lv = ng.interface.new_socket("Level", in_out="INPUT", socket_type="NodeSocketInt")
    lv.min_value, lv.default_value = 0, 0
    N = ng.nodes.new
    gin, gout = N("NodeGroupInput"), N("NodeGroupOutput")
    attr = N("GeometryNodeInputNamedAttribute")
    attr.data_type = "INT"
    attr.inputs["Name"].default_value = "level"
    cmp = N("FunctionNodeCompare")
    cmp.data_type, cmp.operation = "INT", "NOT_EQUAL"
    a = next(s for s in cmp.inputs if s.identifier == "A_INT")
    b = next(s for s in cmp.inputs if s.identifier == "B_INT")
    ng.links.new(attr.outputs["Attribute"], a)
    ng.links.new(gin.outputs["Level"], b)
    delete = N("GeometryNodeDeleteGeometry")
    delete.domain = "POINT"
    ng.links.new(gin.outputs["Geometry"], delete.inputs["Geometry"])
    ng.links.new(cmp.outputs["Result"], delete.inputs["Selection"])
    # A coarse level inspected alone shows its stand-ins whatever the budget: clear their
    # "retire" attribute (preview.py), which would otherwise hide them once the template arrived.
    keep = N("GeometryNodeStoreNamedAttribute")
    keep.data_type, keep.domain = "INT", "POINT"
    keep.inputs["Name"].default_value = "retire"
    next(s for s in keep.inputs if s.name == "Value" and s.enabled).default_value = 0
    ng.links.new(delete.outputs["Geometry"], keep.inputs["Geometry"])
    ng.links.new(keep.outputs["Geometry"], gout.inputs["Geometry"])
    for i, node in enumerate(ng.nodes):
        node.location = (200 * i, 0)
    return ng


def set_level_only(obj, level):
    """Show only the preview's Gaussians of ``level`` (a Geometry Nodes filter first in the
    preview's modifier stack); a negative level removes the filter (all levels)."""
    mod = obj.modifiers.get(LEVEL_MODIFIER)
    if level < 0:
        if mod is not None:
            ng = mod.node_group
            obj.modifiers.remove(mod)
            if ng is not None and ng.users == 0:
                bpy.data.node_groups.remove(ng)
        return
    if mod is None:
        mod = obj.modifiers.new(LEVEL_MODIFIER, "NODES")
        mod.node_group = _level_group()
        obj.modifiers.move(len(obj.modifiers) - 1, 0)  # before the splat modifier
    key = next(
        it.identifier
        for it in mod.node_group.interface.items_tree
        if it.item_type == "SOCKET" and it.in_out == "INPUT" and it.name == "Level"
    )
    mod[key] = int(level)
    obj.update_tag()
