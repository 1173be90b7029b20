"""The splat look in Cycles and EEVEE: each Gaussian drawn as its own 3D Gaussian seen along
the view ray, composited front to back with its opacity.

Geometry Nodes (preview.splat_group) instances a hull on every point that covers the splat
as the rasteriser draws it (its 0.3 px² dilation ε included, out to its 1/255 cut-off
radius k = sqrt(2 ln(255 o))): by default a camera card (a quad through the centre,
parallel to the image plane, so Cycles composites splats in view-depth order like the
rasteriser), or a closed ellipsoid in the splat's frame. The hull is only a proxy that
bounds where the Gaussian is visible. The material evaluates the Gaussian exactly on the
ray, in world space, from the centre and σ-scaled axes the Geometry Nodes store on each
instance (pa_center, pa_axis_x/y/z): with x = hit point − centre and D the view direction,
in the splat's frame w_i = 1/(σ_i² + ε) and the ray passes the centre at squared Mahalanobis
distance d² = Σ w x'² − (Σ w x'D')²/Σ w D'²; the ray's peak response is exp(−d²/2). That is
the projected ellipse with its Gaussian falloff, for any orientation and anisotropy and any
hull. Colour comes from the point's linear "color" attribute as emission (no lighting, like
the rasteriser), alpha = opacity · exp(−d²/2) clamped to [1/255, 0.99] like the
rasteriser's, and back faces are transparent so each Gaussian counts once. ε = 0.3·(z/f)²
needs f, the focal length in pixels: a value node in the material and in the group that
``configure_scene`` sets from the scene camera and resolution.

Cycles composites the hulls along each ray in hit order; EEVEE needs an order-independent
method, so the material uses Dithered (stochastic) transparency, which converges to the same
compositing with enough render samples. ``configure_scene`` sets what a correct render needs
(enough transparent bounces for hundreds of overlapping splats, the Standard view transform
so colours are the avatar's own sRGB values) and, opt-in, the "as trained" compositing:
sRGB-encoded colours blended as they are under the Raw view transform, as in training.
"""

import math

import bpy

from ..core.bridge.transforms import blender_intrinsics

MATERIAL_NAME = "PA Splat"
VERSION = 5
ALPHA_MAX = 0.99  # the rasteriser's per-splat alpha clamp
EPS2D = 0.3  # the rasteriser's screen-space dilation (px²), which training saw
ALPHA_MIN = 1.0 / 255.0  # below this the rasteriser skips a splat
FOCAL_NODE = "pa_focal_px"
AS_TRAINED_NODE = "pa_as_trained"  # 1: emit sRGB-encoded colours (with the Raw view transform)


def _math(nt, op, a, b=None, clamp=False):
    node = nt.nodes.new("ShaderNodeMath")
    node.operation = op
    node.use_clamp = clamp
    for i, v in enumerate((a, b)):
        if v is None:
            continue
        if isinstance(v, (int, float)):
            node.inputs[i].default_value = float(v)
        else:
            nt.links.new(v, node.inputs[i])
    return node.outputs[0]


def _vmath(nt, op, *inputs):
    """A Vector Math node; each input is a socket, a float (all three components) or None."""
    node = nt.nodes.new("ShaderNodeVectorMath")
    node.operation = op
    slots = [node.inputs[0], node.inputs["Scale"]] if op == "SCALE" else list(node.inputs)[:3]
    for slot, v in zip(slots, inputs):
        if v is None:
            continue
        if isinstance(v, (int, float)):
            slot.default_value = float(v) if op == "SCALE" and slot.name == "Scale" else (float(v),) * 3
        else:
            nt.links.new(v, slot)
    return node.outputs["Value"] if op in ("DOT_PRODUCT", "LENGTH", "DISTANCE") else node.outputs["Vector"]


def _srgb_encode(nt, lin):
    """The sRGB transfer function per channel (linear below 0.0031308, power above)."""
    hi = _vmath(nt, "MULTIPLY_ADD", _vmath(nt, "POWER", _vmath(nt, "MAXIMUM", lin, 0.0), 1 / 2.4), 1.055, -0.055)
    lo = _vmath(nt, "SCALE", lin, 12.92)
    step = _vmath(nt, "MULTIPLY_ADD", _vmath(nt, "SIGN", _vmath(nt, "SUBTRACT", lin, 0.0031308)), 0.5, 0.5)
    return _vmath(nt, "MULTIPLY_ADD", step, _vmath(nt, "SUBTRACT", hi, lo), lo)


def splat_material(name=MATERIAL_NAME):
    """The splat material (rebuilt when an older version is found under the same name)."""
    mat = bpy.data.materials.get(name)
    if mat is not None and mat.get("pa_version") == VERSION:
        return mat
    mat = mat or bpy.data.materials.new(name)
    mat["pa_version"] = VERSION
    mat.use_nodes = True
    if hasattr(mat, "surface_render_method"):  # EEVEE: order-independent transparency
        mat.surface_render_method = "DITHERED"
    if hasattr(mat, "use_transparent_shadow"):
        mat.use_transparent_shadow = True
    mat.use_backface_culling = True  # EEVEE viewport; the shader also drops back faces for Cycles
    nt = mat.node_tree
    nt.nodes.clear()
    N = nt.nodes.new
    out = N("ShaderNodeOutputMaterial")
    col = N("ShaderNodeAttribute")
    col.attribute_type, col.attribute_name = "INSTANCER", "color"
    opa = N("ShaderNodeAttribute")
    opa.attribute_type, opa.attribute_name = "INSTANCER", "opacity"
    geo = N("ShaderNodeNewGeometry")
    # In world space: x = hit point − centre, D = the view direction; the splat's axes come
    # scaled by σ (A_i = σ_i r_i). The rasteriser dilates every projected Gaussian by EPS2D
    # px² (and training saw that): in world units ε = EPS2D·(z/f)² added to each σ², so in
    # the splat's frame x'_i = r_i·x, w_i = 1/(σ_i² + ε) and
    # d² = Σ w x'² − (Σ w x' D')² / Σ w D'² (the ray's closest approach, Mahalanobis).
    centre = N("ShaderNodeAttribute")
    centre.attribute_type, centre.attribute_name = "INSTANCER", "pa_center"
    x = _vmath(nt, "SUBTRACT", geo.outputs["Position"], centre.outputs["Vector"])
    d_vec = geo.outputs["Incoming"]
    cam = N("ShaderNodeCameraData")
    focal = N("ShaderNodeValue")
    focal.name = focal.label = FOCAL_NODE
    focal.outputs[0].default_value = 1e9  # no dilation until configure_scene knows the camera
    px = _math(nt, "DIVIDE", cam.outputs["View Z Depth"], focal.outputs[0])
    eps = _math(nt, "MULTIPLY", _math(nt, "MULTIPLY", px, px), EPS2D)
    pkp = pkd = dkd = None
    for axis in "xyz":
        a_attr = N("ShaderNodeAttribute")
        a_attr.attribute_type, a_attr.attribute_name = "INSTANCER", f"pa_axis_{axis}"
        a_vec = a_attr.outputs["Vector"]
        r = _vmath(nt, "NORMALIZE", a_vec)
        w = _math(nt, "DIVIDE", 1.0, _math(nt, "ADD", _vmath(nt, "DOT_PRODUCT", a_vec, a_vec), eps))
        xi = _vmath(nt, "DOT_PRODUCT", r, x)
        di = _vmath(nt, "DOT_PRODUCT", r, d_vec)
        terms = (
            _math(nt, "MULTIPLY", w, _math(nt, "MULTIPLY", xi, xi)),
            _math(nt, "MULTIPLY", w, _math(nt, "MULTIPLY", xi, di)),
            _math(nt, "MULTIPLY", w, _math(nt, "MULTIPLY", di, di)),
        )
        if pkp is None:
            pkp, pkd, dkd = terms
        else:
            pkp, pkd, dkd = (_math(nt, "ADD", u, v) for u, v in zip((pkp, pkd, dkd), terms))
    dkd = _math(nt, "MAXIMUM", dkd, 1e-30)
    d2 = _math(nt, "SUBTRACT", pkp, _math(nt, "DIVIDE", _math(nt, "MULTIPLY", pkd, pkd), dkd))
    fall = _math(nt, "EXPONENT", _math(nt, "MULTIPLY", _math(nt, "MAXIMUM", d2, 0.0), -0.5))
    alpha = _math(nt, "MINIMUM", _math(nt, "MULTIPLY", fall, opa.outputs["Fac"]), ALPHA_MAX)
    # The rasteriser skips a splat where its alpha is below 1/255 (the hull's edge is there).
    alpha = _math(nt, "MULTIPLY", alpha, _math(nt, "GREATER_THAN", alpha, ALPHA_MIN))
    front = _math(nt, "SUBTRACT", 1.0, geo.outputs["Backfacing"])
    alpha = _math(nt, "MULTIPLY", alpha, front)
    # "As trained": emit the sRGB-encoded colour, composited as-is and shown by the Raw view
    # transform, i.e. blending in sRGB like the rasteriser; 0 emits the scene-linear colour.
    as_trained = N("ShaderNodeValue")
    as_trained.name = as_trained.label = AS_TRAINED_NODE
    as_trained.outputs[0].default_value = 0.0
    lin = col.outputs["Vector"]
    color = _vmath(
        nt, "ADD", lin, _vmath(nt, "SCALE", _vmath(nt, "SUBTRACT", _srgb_encode(nt, lin), lin), as_trained.outputs[0])
    )
    emit = N("ShaderNodeEmission")
    nt.links.new(color, emit.inputs["Color"])
    clear = N("ShaderNodeBsdfTransparent")
    mix = N("ShaderNodeMixShader")
    nt.links.new(alpha, mix.inputs[0])
    nt.links.new(clear.outputs[0], mix.inputs[1])
    nt.links.new(emit.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], out.inputs["Surface"])
    for i, node in enumerate(nt.nodes):
        node.location = (180 * (i % 7), -180 * (i // 7))
    mat.diffuse_color = (0.8, 0.6, 0.5, 1.0)
    return mat


def _value_nodes(name, mat=None):
    """The material's and the splat Geometry Nodes group's value nodes of this name."""
    from .preview import GROUP_NAME

    mat = mat or bpy.data.materials.get(MATERIAL_NAME)
    trees = [mat.node_tree if mat is not None else None, bpy.data.node_groups.get(GROUP_NAME)]
    return [t.nodes[name] for t in trees if t is not None and name in t.nodes]


_KINDS = {"ORTHO": "orthographic", "PANO": "panoramic"}


def render_size(scene):
    """The render's size in pixels, (width, height), as Blender computes it (resolution ×
    percentage / 100, rounded down); ValueError where that leaves no pixel."""
    r = scene.render
    w = r.resolution_x * r.resolution_percentage // 100
    h = r.resolution_y * r.resolution_percentage // 100
    if w < 1 or h < 1:
        raise ValueError(
            f"the render would be {w}×{h} px ({r.resolution_x}×{r.resolution_y} at "
            f"{r.resolution_percentage} %): raise the resolution or its percentage"
        )
    return w, h


def scene_camera(scene):
    """The scene camera object and its settings at the render size, as keyword arguments for
    core.bridge.transforms (``blender_intrinsics``, ``camera_from_blender``): lens, sensor
    size and fit, shifts, width, height and pixel aspect. ValueError, saying why, where the
    splats cannot be drawn for it: no camera, an object that is not a camera, an orthographic
    or panoramic camera (our renderer and the splat dilation are perspective only), a render
    with no pixels."""
    obj = scene.camera
    if obj is None:
        raise ValueError("the scene has no camera: set one in Scene Properties > Camera")
    if obj.type != "CAMERA":
        kind = obj.type.lower()
        raise ValueError(
            f"the scene camera '{obj.name}' is {'an' if kind[0] in 'aeiou' else 'a'} {kind} object, "
            "not a camera: set a camera in Scene Properties > Camera"
        )
    cam = obj.data
    if cam.type != "PERSP":
        kind = _KINDS.get(cam.type, cam.type.lower())
        raise ValueError(
            f"the scene camera '{obj.name}' is {kind}: splats are drawn for perspective cameras only "
            "(set its Type to Perspective)"
        )
    w, h = render_size(scene)
    r = scene.render
    return obj, dict(
        lens=cam.lens,
        sensor_width=cam.sensor_width,
        sensor_height=cam.sensor_height,
        sensor_fit=cam.sensor_fit,
        shift_x=cam.shift_x,
        shift_y=cam.shift_y,
        width=w,
        height=h,
        pixel_aspect=(r.pixel_aspect_x, r.pixel_aspect_y),
    )


def set_focal(scene, mat=None):
    """The scene camera's focal length in pixels, for the dilation in the material and in
    the hull (it changes with the camera and the resolution: set when a preview is made, before
    every render and by Splat Render Settings). Returns it, or None where there is nothing to
    set or no perspective camera (``scene_camera`` says why). With non-square pixels (fx ≠ fy)
    the dilation, isotropic in world units, uses √(fx·fy): the rasteriser's dilated area. Writes
    only a changed value (a write re-evaluates every preview)."""
    nodes = _value_nodes(FOCAL_NODE, mat)
    if not nodes:
        return None
    try:
        _, settings = scene_camera(scene)
    except ValueError:
        return None
    fx, fy, _, _ = blender_intrinsics(**settings)
    f = math.sqrt(fx * fy)
    for node in nodes:
        if abs(node.outputs[0].default_value - f) > 1e-4 * f:
            node.outputs[0].default_value = f
    return f


def focal_warning(scene):
    """Set the splats' focal length from ``scene``'s camera; "" when set, else a warning saying
    why the splats go without their dilation (the rasteriser's 0.3 px²) until it can be."""
    if not _value_nodes(FOCAL_NODE):
        return ""
    try:
        scene_camera(scene)
    except ValueError as exc:
        return (
            f"splats drawn without their {EPS2D} px² dilation: {exc} (their focal length is set "
            "from the scene camera when rendering, and by Splat Render Settings)"
        )
    set_focal(scene)
    return ""


def configure_scene(scene, transparent_bounces=512, min_transparent_bounces=None, as_trained=False):
    """Render settings the splat look needs; returns {setting: (old, new)} of what changed.

    ``as_trained`` composites the avatar's sRGB-encoded colours as they are and shows them
    with the Raw view transform: exactly how the avatar was trained (and how our rasteriser
    draws it), but other objects in the scene are then shown unencoded (too dark) and light
    does not mix with the splats correctly. Off (the default), splats emit scene-linear
    colours under the Standard view transform, like any other object."""
    changed = {}
    f = set_focal(scene)
    if f is not None:
        changed["splat focal px"] = (None, round(f, 2))

    def put(owner, attr, value, label):
        old = getattr(owner, attr)
        if old != value:
            setattr(owner, attr, value)
            changed[label] = (old, value)

    for node in _value_nodes(AS_TRAINED_NODE):
        put(node.outputs[0], "default_value", float(as_trained), "splat colours as trained")
    put(scene.view_settings, "view_transform", "Raw" if as_trained else "Standard", "view_transform")
    put(scene.view_settings, "look", "None", "look")
    cy = getattr(scene, "cycles", None)
    if cy is not None:
        if cy.transparent_max_bounces < transparent_bounces:
            put(cy, "transparent_max_bounces", transparent_bounces, "cycles.transparent_max_bounces")
        # Past the minimum, Cycles ends paths through transparency at random (Russian
        # roulette): unbiased, but with hundreds of faint splats per pixel it is the grain.
        low = transparent_bounces if min_transparent_bounces is None else min_transparent_bounces
        if cy.min_transparent_bounces < low:
            put(cy, "min_transparent_bounces", low, "cycles.min_transparent_bounces")
    return changed


class PA_OT_splat_render_settings(bpy.types.Operator):
    """Set the scene's render settings the splat look needs (Standard view transform, enough
    transparent bounces for overlapping splats)"""

    bl_idname = "render.progressive_avatars_splat_settings"
    bl_label = "Splat Render Settings"
    bl_options = {"REGISTER", "UNDO"}

    as_trained: bpy.props.BoolProperty(
        name="As Trained",
        description="Composite the avatar's sRGB colours as they are under the Raw view transform: "
        "exactly as the avatar was trained, but other objects and lights no longer look right",
        default=False,
    )

    def execute(self, context):
        changed = configure_scene(context.scene, as_trained=self.as_trained)
        text = ", ".join(f"{k}: {a} → {b}" for k, (a, b) in changed.items()) or "already set"
        try:
            scene_camera(context.scene)
        except ValueError as exc:  # the rest is set; the dilation needs a perspective camera
            self.report({"WARNING"}, f"Splat render settings: {text}; splat focal length not set: {exc}")
            return {"FINISHED"}
        self.report({"INFO"}, f"Splat render settings: {text}")
        return {"FINISHED"}


classes = (PA_OT_splat_render_settings,)
