"""The splat preview: a point per Gaussian carrying its attributes, drawn by Geometry Nodes.

Points are grouped by root face (the layout the per-frame evaluator writes fastest); their
"rank" attribute is their stream position, and the modifier deletes those whose rank reaches
the "Count" input (and coarse stand-ins once Count reaches their "retire" attribute: the
template faces of their region have arrived; 0 for every other point), so moving the
budget slider only sets one modifier input. Each remaining point instances
a hull that covers the Gaussian as the rasteriser draws it (dilated, out to its 1/255
cut-off): a camera-facing card by default, or an ellipsoid in the splat's frame; the
material (splat_look) reads colour, opacity, centre and axes from the instance and evaluates
the Gaussian on each view ray, so every splat shows as its oriented ellipse.
"""

import bpy

GROUP_NAME = "PA Splats"
MATERIAL_NAME = "PA Splat"
MODIFIER_NAME = "PA Splats"
GROUP_VERSION = 6
EPS2D = 0.3  # the rasteriser's screen-space dilation (px²), which training saw
FOCAL_NODE = "pa_focal_px"  # focal length in pixels (set with the material's by splat_look.set_focal)
EXTENT_NODE = "pa_extent"  # multiplier on the hull's cut-off radius (1: the rasteriser's own)
MIN_CUT = 1.65  # 255·o floor: a hull of at least 1σ, even for splats the rasteriser skips
E = 2.718281828459045
ELLIPSOID_EXTENT = 3.0  # the ellipsoid hull's radius in σ (Camera Cards off)

# name -> (attribute type, foreach field, width)
ATTRIBUTES = {
    "rotation": ("QUATERNION", "value", 4),
    "scale": ("FLOAT_VECTOR", "vector", 3),
    "opacity": ("FLOAT", "value", 1),
    "color": ("FLOAT_COLOR", "color", 4),
    "level": ("INT", "value", 1),
    "rank": ("INT", "value", 1),
    "retire": ("INT", "value", 1),
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


def _vec(tree, op, a, b):
    node = tree.nodes.new("ShaderNodeVectorMath")
    node.operation = op
    _link(tree, a, node.inputs[0])
    _link(tree, b, node.inputs["Scale"] if op == "SCALE" else node.inputs[1])
    return node.outputs["Value"] if op in ("DISTANCE", "LENGTH", "DOT_PRODUCT") else node.outputs["Vector"]


def _flt(tree, op, a, b=None):
    node = tree.nodes.new("ShaderNodeMath")
    node.operation = op
    for i, v in enumerate((a, b)):
        if isinstance(v, (int, float)):
            node.inputs[i].default_value = float(v)
        elif v is not None:
            _link(tree, v, node.inputs[i])
    return node.outputs[0]


def _combine(tree, v, values=None):
    node = tree.nodes.new("ShaderNodeCombineXYZ")
    for axis in "XYZ":
        if values is not None:
            node.inputs[axis].default_value = values.get(axis, 0.0)
        elif isinstance(v, (int, float)):
            node.inputs[axis].default_value = float(v)
        else:
            _link(tree, v, node.inputs[axis])
    return node.outputs[0]


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
    cards = ng.interface.new_socket("Camera Cards", in_out="INPUT", socket_type="NodeSocketBool")
    cards.default_value = True
    # Cards face the scene camera, so an orbiting viewport would see them edge-on: by default
    # they are used for renders only and the viewport shows the ellipsoids (right from any view).
    in_view = ng.interface.new_socket("Cards in Viewport", in_out="INPUT", socket_type="NodeSocketBool")
    in_view.default_value = False
    N = ng.nodes.new
    gin, gout = N("NodeGroupInput"), N("NodeGroupOutput")

    def attr(name, data_type):
        node = N("GeometryNodeInputNamedAttribute")
        node.data_type = data_type
        node.inputs["Name"].default_value = name
        return node.outputs["Attribute"]

    def compare(op, a, b):
        node = N("FunctionNodeCompare")
        node.data_type, node.operation = "INT", op
        for key, v in (("A_INT", a), ("B_INT", b)):
            if isinstance(v, int):
                _by_id(node.inputs, key).default_value = v
            else:
                _link(ng, v, _by_id(node.inputs, key))
        return node.outputs["Result"]

    def boolean(op, a, b):
        node = N("FunctionNodeBooleanMath")
        node.operation = op
        _link(ng, a, node.inputs[0])
        _link(ng, b, node.inputs[1])
        return node.outputs[0]

    retire = attr("retire", "INT")
    not_sent = compare("GREATER_EQUAL", attr("rank", "INT"), gin.outputs["Count"])
    retired = boolean("AND", compare("GREATER_THAN", retire, 0), compare("GREATER_EQUAL", gin.outputs["Count"], retire))
    delete = N("GeometryNodeDeleteGeometry")
    delete.domain = "POINT"
    _link(ng, gin.outputs["Geometry"], delete.inputs["Geometry"])
    _link(ng, boolean("OR", not_sent, retired), delete.inputs["Selection"])

    # Two hulls, either of which covers each splat as the rasteriser draws it: out to its
    # cut-off radius k = sqrt(2 ln(255 o)) (alpha below 1/255 there; 3.33 at the 0.99 clamp)
    # of the dilated Gaussian, σ² + ε with ε = EPS2D·(d/f)², d the distance to the active
    # camera (≥ the view depth the material uses). The material evaluates the Gaussian on the
    # ray in world space, whatever the hull, so the hull decides only what is covered and in
    # which order Cycles composites the splats: it composites in hit order.
    # - Camera Cards (default): a flat quad through the centre, parallel to the camera's
    #   image plane, sized to the footprint's extent along the camera's x and y. Every ray
    #   hits it at the centre's view depth, so splats composite in order of view depth, as
    #   the rasteriser sorts them. Exact for the scene camera; from other views (orbiting
    #   the viewport) the cards are seen at an angle and clip their splats.
    # - Ellipsoids: a closed ico-sphere hull in the splat's own frame, right from every
    #   view, but composited in order of where rays enter the hulls, which puts a large
    #   splat in front of smaller ones around it (measured in docs/BLENDER_SPLATS.md).
    rot = attr("rotation", "QUATERNION")
    sigma = _vec(ng, "SCALE", attr("scale", "FLOAT_VECTOR"), gin.outputs["Size"])
    camera = N("GeometryNodeObjectInfo")
    camera.transform_space = "RELATIVE"  # the camera in this object's space, like the points
    _link(ng, N("GeometryNodeInputActiveCamera").outputs[0], camera.inputs["Object"])
    position = N("GeometryNodeInputPosition").outputs[0]
    dist = _vec(ng, "DISTANCE", position, camera.outputs["Location"])
    focal = N("ShaderNodeValue")
    focal.name = focal.label = FOCAL_NODE
    focal.outputs[0].default_value = 1e9  # no dilation until Splat Render Settings knows the camera
    px = _flt(ng, "DIVIDE", dist, focal.outputs[0])
    eps = _flt(ng, "MULTIPLY", _flt(ng, "MULTIPLY", px, px), EPS2D)
    cut = _flt(ng, "MULTIPLY", attr("opacity", "FLOAT"), 255.0)
    cut = _flt(ng, "SQRT", _flt(ng, "MULTIPLY", _flt(ng, "LOGARITHM", _flt(ng, "MAXIMUM", cut, MIN_CUT), E), 2.0))
    extent = N("ShaderNodeValue")
    extent.name = extent.label = EXTENT_NODE
    extent.outputs[0].default_value = 1.0
    cut = _flt(ng, "MULTIPLY", cut, extent.outputs[0])

    def rotate(vector, rotation):
        node = N("FunctionNodeRotateVector")
        _link(ng, vector, node.inputs["Vector"])
        _link(ng, rotation, node.inputs["Rotation"])
        return node.outputs[0]

    def unit(axis):
        return _combine(ng, None, {axis: 1.0})

    # The splat's axes scaled by σ, in this object's space (local) and in world space (for
    # the material, which works in world space: the object may be moved, rotated, scaled).
    me = N("GeometryNodeObjectInfo")
    me.transform_space = "ORIGINAL"
    _link(ng, N("GeometryNodeSelfObject").outputs[0], me.inputs["Object"])
    axes = []
    for i, axis in enumerate("XYZ"):
        sep = N("ShaderNodeSeparateXYZ")
        _link(ng, sigma, sep.inputs[0])
        axes.append(_vec(ng, "SCALE", rotate(unit(axis), rot), sep.outputs[i]))
    # Card extents along the camera's x and y: k·sqrt(Σ_i σ_i² (c·r_i)² + ε).
    card = []
    for axis in "XY":
        c = rotate(unit(axis), camera.outputs["Rotation"])
        var = eps
        for a in axes:
            dot = _vec(ng, "DOT_PRODUCT", a, c)
            var = _flt(ng, "ADD", var, _flt(ng, "MULTIPLY", dot, dot))
        card.append(_flt(ng, "MULTIPLY", _flt(ng, "SQRT", var), cut))
    card_scale = N("ShaderNodeCombineXYZ")
    _link(ng, card[0], card_scale.inputs["X"])
    _link(ng, card[1], card_scale.inputs["Y"])
    card_scale.inputs["Z"].default_value = 1.0
    quad = N("GeometryNodeMeshGrid")  # [-1, 1]², normal +Z: towards the camera once rotated
    quad.inputs["Size X"].default_value = quad.inputs["Size Y"].default_value = 2.0
    quad.inputs["Vertices X"].default_value = quad.inputs["Vertices Y"].default_value = 2

    # Ellipsoids: an ico-sphere of radius ELLIPSOID_EXTENT in the splat's frame, scaled by σ
    # (undilated). Deliberately tighter than the cut-off of the dilated splat: Cycles
    # composites in the order rays enter these hulls, and larger hulls put more splats in
    # front of their neighbours (measured worse: docs/BLENDER_SPLATS.md).
    ico = N("GeometryNodeMeshIcoSphere")
    ico.inputs["Radius"].default_value = ELLIPSOID_EXTENT
    _link(ng, gin.outputs["Detail"], ico.inputs["Subdivisions"])
    hull = sigma

    not_viewport = N("FunctionNodeBooleanMath")
    not_viewport.operation = "NOT"
    _link(ng, N("GeometryNodeIsViewport").outputs[0], not_viewport.inputs[0])
    here = N("FunctionNodeBooleanMath")
    here.operation = "OR"
    _link(ng, gin.outputs["Cards in Viewport"], here.inputs[0])
    _link(ng, not_viewport.outputs[0], here.inputs[1])
    use_cards = N("FunctionNodeBooleanMath")
    use_cards.operation = "AND"
    _link(ng, gin.outputs["Camera Cards"], use_cards.inputs[0])
    _link(ng, here.outputs[0], use_cards.inputs[1])
    cards = use_cards.outputs[0]
    shape = N("GeometryNodeSwitch")
    shape.input_type = "GEOMETRY"
    _link(ng, cards, shape.inputs["Switch"])
    _link(ng, ico.outputs["Mesh"], shape.inputs["False"])
    _link(ng, quad.outputs["Mesh"], shape.inputs["True"])
    setmat = N("GeometryNodeSetMaterial")
    setmat.inputs["Material"].default_value = splat_material()
    _link(ng, shape.outputs[0], setmat.inputs["Geometry"])
    rot_sw = N("GeometryNodeSwitch")
    rot_sw.input_type = "ROTATION"
    _link(ng, cards, rot_sw.inputs["Switch"])
    _link(ng, rot, rot_sw.inputs["False"])
    _link(ng, camera.outputs["Rotation"], rot_sw.inputs["True"])
    scale_sw = N("GeometryNodeSwitch")
    scale_sw.input_type = "VECTOR"
    _link(ng, cards, scale_sw.inputs["Switch"])
    _link(ng, hull, scale_sw.inputs["False"])
    _link(ng, card_scale.outputs[0], scale_sw.inputs["True"])

    # What the material reads (world space): the centre and the three σ-scaled axes.
    points = delete.outputs["Geometry"]
    world = [("pa_center", "FunctionNodeTransformPoint", "Vector", position)]
    world += [(f"pa_axis_{a.lower()}", "FunctionNodeTransformDirection", "Direction", v) for a, v in zip("XYZ", axes)]
    for name, kind, socket, value in world:
        tf = N(kind)
        _link(ng, value, tf.inputs[socket])
        _link(ng, me.outputs["Transform"], tf.inputs["Transform"])
        store = N("GeometryNodeStoreNamedAttribute")
        store.data_type, store.domain = "FLOAT_VECTOR", "POINT"
        store.inputs["Name"].default_value = name
        _link(ng, points, store.inputs["Geometry"])
        _link(ng, tf.outputs[0], store.inputs["Value"])
        points = store.outputs["Geometry"]
    inst = N("GeometryNodeInstanceOnPoints")
    _link(ng, points, inst.inputs["Points"])
    _link(ng, setmat.outputs["Geometry"], inst.inputs["Instance"])
    _link(ng, rot_sw.outputs[0], inst.inputs["Rotation"])
    _link(ng, scale_sw.outputs[0], inst.inputs["Scale"])
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
    static attributes (opacity, colour, level, rank, retire; a missing retire reads 0: never);
    positions and frames come per frame."""
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
