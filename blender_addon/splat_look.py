"""The splat look in Cycles and EEVEE: each Gaussian drawn as its own 3D Gaussian seen along
the view ray, composited front to back with its opacity.

Geometry Nodes instances a closed hull (an ico-sphere of radius 3σ in the Gaussian's own
frame) on every point, rotated by its quaternion and scaled by its scales; the hull is only a
proxy that bounds where the Gaussian is visible. The material evaluates the Gaussian
exactly on the ray that hits the hull's front face: in the instance's object space (where the
Gaussian is the unit normal distribution) a ray through P with direction D passes the centre
at squared distance d² = |P|² − (P·D̂)², and the ray's peak response is exp(−d²/2). That is
the projected ellipse with its Gaussian falloff, for any orientation and anisotropy and from
any side (no camera-facing trick, no dependence on the hull's tessellation). Colour comes
from the point's linear "color" attribute as emission (no lighting, like the rasteriser),
alpha = opacity · exp(−d²/2), and the back faces of each hull are transparent so each
Gaussian counts once.

Cycles composites the hulls along each ray in hit order; EEVEE needs an order-independent
method, so the material uses Dithered (stochastic) transparency, which converges to the same
compositing with enough render samples. ``configure_scene`` sets what a correct render needs
(enough transparent bounces for hundreds of overlapping splats, the Standard view transform
so colours are the avatar's own sRGB values).
"""

import bpy

MATERIAL_NAME = "PA Splat"
VERSION = 2
EXTENT = 3.0  # hull radius in standard deviations (the rasteriser cuts at ~3σ too)
ALPHA_MAX = 0.99  # the rasteriser's per-splat alpha clamp


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


def _vmath(nt, op, a, b=None):
    node = nt.nodes.new("ShaderNodeVectorMath")
    node.operation = op
    nt.links.new(a, node.inputs[0])
    if b is not None:
        nt.links.new(b, node.inputs[1])
    return node.outputs["Value"] if op in ("DOT_PRODUCT", "LENGTH") else node.outputs["Vector"]


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
    tex = N("ShaderNodeTexCoord")  # "Object": the hit point in the instance's unit-Gaussian frame
    geo = N("ShaderNodeNewGeometry")
    to_obj = N("ShaderNodeVectorTransform")
    to_obj.vector_type, to_obj.convert_from, to_obj.convert_to = "VECTOR", "WORLD", "OBJECT"
    nt.links.new(geo.outputs["Incoming"], to_obj.inputs["Vector"])
    d_hat = _vmath(nt, "NORMALIZE", to_obj.outputs["Vector"])
    p = tex.outputs["Object"]
    p_len2 = _vmath(nt, "DOT_PRODUCT", p, p)
    p_d = _vmath(nt, "DOT_PRODUCT", p, d_hat)
    d2 = _math(nt, "SUBTRACT", p_len2, _math(nt, "MULTIPLY", p_d, p_d))
    fall = _math(nt, "EXPONENT", _math(nt, "MULTIPLY", _math(nt, "MAXIMUM", d2, 0.0), -0.5))
    alpha = _math(nt, "MINIMUM", _math(nt, "MULTIPLY", fall, opa.outputs["Fac"]), ALPHA_MAX)
    front = _math(nt, "SUBTRACT", 1.0, geo.outputs["Backfacing"])
    alpha = _math(nt, "MULTIPLY", alpha, front)
    emit = N("ShaderNodeEmission")
    nt.links.new(col.outputs["Color"], emit.inputs["Color"])
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


def configure_scene(scene, transparent_bounces=512, min_transparent_bounces=None):
    """Render settings the splat look needs; returns {setting: (old, new)} of what changed."""
    changed = {}

    def put(owner, attr, value, label):
        old = getattr(owner, attr)
        if old != value:
            setattr(owner, attr, value)
            changed[label] = (old, value)

    put(scene.view_settings, "view_transform", "Standard", "view_transform")
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

    def execute(self, context):
        changed = configure_scene(context.scene)
        text = ", ".join(f"{k}: {a} → {b}" for k, (a, b) in changed.items()) or "already set"
        self.report({"INFO"}, f"Splat render settings: {text}")
        return {"FINISHED"}


classes = (PA_OT_splat_render_settings,)
