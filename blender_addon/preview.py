"""The splat preview: a point per Gaussian carrying its attributes, drawn by Geometry Nodes.

Points are grouped by root face (the layout the per-frame evaluator writes fastest); their
"rank" attribute is their stream position, and the modifier deletes those whose rank reaches
the "Count" input, so moving the budget slider only sets one modifier input. Each remaining point instances
an ico-sphere of radius 3 (3σ), rotated by the point's quaternion and scaled by its
scale; the material (splat_look) reads colour and opacity from the instance and evaluates
the Gaussian on each view ray, so every splat shows as its oriented ellipse.
"""

import bpy

GROUP_NAME = "PA Splats"
MATERIAL_NAME = "PA Splat"
MODIFIER_NAME = "PA Splats"
GROUP_VERSION = 2
EXTENT = 3.0  # sphere radius in standard deviations

# name -> (attribute type, foreach field, width)
ATTRIBUTES = {
    "rotation": ("QUATERNION", "value", 4),
    "scale": ("FLOAT_VECTOR", "vector", 3),
    "opacity": ("FLOAT", "value", 1),
    "color": ("FLOAT_COLOR", "color", 4),
    "level": ("INT", "value", 1),
    "rank": ("INT", "value", 1),
}


def _link(tree, a, b):
    tree.links.new(a, b)


def _by_id(sockets, identifier):
    # Collections index sockets by name; several of a node's sockets can share one.
    return next(s for s in sockets if s.identifier == identifier)


def _socket(ng, name, in_out="INPUT"):
    for item in ng.interface.items_tree:
        if item.item_type == "SOCKET" and item.in_out == in_out and item.name == name:
            return item
    raise KeyError(name)


def input_identifier(ng, name) -> str:
    """Modifier keys are socket identifiers (e.g. "Socket_2"), not names: look them up."""
    return _socket(ng, name).identifier


def splat_material():
    # The look itself (ray-exact Gaussian falloff for Cycles and EEVEE) lives in splat_look.
    from . import splat_look

    return splat_look.splat_material(MATERIAL_NAME)


def splat_group():
    ng = bpy.data.node_groups.get(GROUP_NAME)
    if ng is not None and ng.get("pa_version") == GROUP_VERSION:
        return ng
    ng = ng or bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    ng["pa_version"] = GROUP_VERSION
    ng.nodes.clear()
    ng.interface.clear()
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    count = ng.interface.new_socket("Count", in_out="INPUT", socket_type="NodeSocketInt")
    count.min_value, count.default_value = 0, 0
    size = ng.interface.new_socket("Size", in_out="INPUT", socket_type="NodeSocketFloat")
    size.min_value, size.default_value = 0.0, 1.0
    pts = ng.interface.new_socket("Points Only", in_out="INPUT", socket_type="NodeSocketBool")
    pts.default_value = False
    detail = ng.interface.new_socket("Detail", in_out="INPUT", socket_type="NodeSocketInt")
    detail.min_value, detail.max_value, detail.default_value = 1, 4, 2
    N = ng.nodes.new
    gin, gout = N("NodeGroupInput"), N("NodeGroupOutput")

    def attr(name, data_type):
        node = N("GeometryNodeInputNamedAttribute")
        node.data_type = data_type
        node.inputs["Name"].default_value = name
        return node.outputs["Attribute"]

    cmp = N("FunctionNodeCompare")
    cmp.data_type, cmp.operation = "INT", "GREATER_EQUAL"
    _link(ng, attr("rank", "INT"), _by_id(cmp.inputs, "A_INT"))
    _link(ng, gin.outputs["Count"], _by_id(cmp.inputs, "B_INT"))
    delete = N("GeometryNodeDeleteGeometry")
    delete.domain = "POINT"
    _link(ng, gin.outputs["Geometry"], delete.inputs["Geometry"])
    _link(ng, cmp.outputs["Result"], delete.inputs["Selection"])

    ico = N("GeometryNodeMeshIcoSphere")
    ico.inputs["Radius"].default_value = EXTENT
    _link(ng, gin.outputs["Detail"], ico.inputs["Subdivisions"])
    # Smooth normals: the material's falloff is a function of the normal, and flat facets
    # would print the icosahedron onto every splat.
    smooth = N("GeometryNodeSetShadeSmooth")
    _link(ng, ico.outputs["Mesh"], smooth.inputs["Geometry"])
    setmat = N("GeometryNodeSetMaterial")
    setmat.inputs["Material"].default_value = splat_material()
    _link(ng, smooth.outputs["Geometry"], setmat.inputs["Geometry"])
    scl = N("ShaderNodeVectorMath")
    scl.operation = "SCALE"
    _link(ng, attr("scale", "FLOAT_VECTOR"), scl.inputs[0])
    _link(ng, gin.outputs["Size"], scl.inputs["Scale"])
    inst = N("GeometryNodeInstanceOnPoints")
    _link(ng, delete.outputs["Geometry"], inst.inputs["Points"])
    _link(ng, setmat.outputs["Geometry"], inst.inputs["Instance"])
    _link(ng, attr("rotation", "QUATERNION"), inst.inputs["Rotation"])
    _link(ng, scl.outputs["Vector"], inst.inputs["Scale"])
    switch = N("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    _link(ng, gin.outputs["Points Only"], switch.inputs["Switch"])
    _link(ng, inst.outputs["Instances"], switch.inputs["False"])
    _link(ng, delete.outputs["Geometry"], switch.inputs["True"])
    _link(ng, switch.outputs[0], gout.inputs["Geometry"])
    for i, node in enumerate(ng.nodes):
        node.location = (200 * (i % 6), -200 * (i // 6))
    return ng


def create_preview_object(name, source, static):
    """A point-only mesh with one vertex per Gaussian, parented to ``source``, carrying the
    static attributes (opacity, colour, level, rank); positions and frames come per frame."""
    n = len(static["rank"])
    me = bpy.data.meshes.new(name)
    me.vertices.add(n)
    for attr_name, (kind, field, _width) in ATTRIBUTES.items():
        me.attributes.new(attr_name, kind, "POINT")
    write_attributes(me, static)
    obj = bpy.data.objects.new(name, me)
    collections = source.users_collection or (bpy.context.scene.collection,)
    collections[0].objects.link(obj)
    obj.parent = source
    obj.matrix_parent_inverse.identity()
    mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    mod.node_group = splat_group()
    return obj


def write_attributes(me, arrays):
    for key, values in arrays.items():
        if key == "position":
            me.attributes["position"].data.foreach_set("vector", values.ravel())
            continue
        kind, field, _ = ATTRIBUTES[key]
        me.attributes[key].data.foreach_set(field, values.ravel())


def set_count(obj, count):
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is None or mod.node_group is None:
        return False
    key = input_identifier(mod.node_group, "Count")
    if mod.get(key) != count:
        mod[key] = int(count)
        obj.update_tag()
    return True
