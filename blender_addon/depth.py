"""Per-face subdivision depth on the mesh: an int face attribute, a corner colour for Solid
mode (face-domain colours do not show there), and a legend stored on the object."""

import numpy as np

from ..core.bridge import preview as preview_data

DEPTH_ATTR = "pa_depth"
COLOR_ATTR = "pa_depth_color"


def apply_depth(obj, forest):
    me = obj.data
    depth = forest.depth_per_root().astype(np.int32)
    if len(me.polygons) != len(depth):
        raise ValueError(f"{obj.name} has {len(me.polygons)} faces, the avatar's template {len(depth)}")
    for name in (DEPTH_ATTR, COLOR_ATTR):
        if name in me.attributes:
            me.attributes.remove(me.attributes[name])
    me.attributes.new(DEPTH_ATTR, "INT", "FACE").data.foreach_set("value", depth)
    totals = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_total", totals)
    colors = preview_data.per_corner(preview_data.depth_colors(depth, forest.max_level), totals)
    attr = me.color_attributes.new(COLOR_ATTR, "FLOAT_COLOR", "CORNER")
    attr.data.foreach_set("color", colors.ravel())
    me.color_attributes.active_color = attr
    legend = obj.pa_mesh.depth_legend
    legend.clear()
    for d, n, rgb in preview_data.depth_legend(depth):
        item = legend.add()
        item.depth, item.faces, item.color = d, n, rgb
    me.update()
    return depth
