"""Add-on preferences: the external Python that has torch/numba (Blender ships neither)."""

import os

import bpy

from . import ADDON_PACKAGE


def _default_python() -> str:
    # A repository checkout keeps its venv next to the sources; an installed extension has none.
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for rel in (".venv/bin/python", ".venv/Scripts/python.exe"):
        cand = os.path.join(root, rel)
        if os.path.isfile(cand):
            return cand
    return ""


class PA_Preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    python_path: bpy.props.StringProperty(
        name="Python",
        subtype="FILE_PATH",
        default="",
        description="Python interpreter with torch and numba installed, used for training and splat rendering",
    )
    train_script: bpy.props.StringProperty(
        name="Train script",
        subtype="FILE_PATH",
        default="",
        description="Optional: a checkout's scripts/train.py to run instead of the extension's own trainer",
    )
    flame_model: bpy.props.StringProperty(
        name="FLAME model",
        subtype="FILE_PATH",
        default="",
        description="Your own FLAME model file (generic_model.pkl / flame2023.pkl), for FLAME parameter sequences",
    )

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "python_path")
        col.prop(self, "train_script")
        col.prop(self, "flame_model")
        if not bpy.app.online_access:
            col.label(text="Online access is off: URL streaming is disabled", icon="INFO")


def get(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon else None


def python_path(context=None) -> str:
    p = get(context)
    path = bpy.path.abspath(p.python_path) if p and p.python_path else _default_python()
    return path or ""


def python_problem(context=None, needs="torch and numba") -> str:
    """Why the configured Python cannot be run ("" when it can), naming the path and where
    to set it."""
    python = python_path(context)
    where = "Preferences > Add-ons > Progressive Avatars > Python"
    if not python:
        return f"No Python set: choose one with {needs} in {where}"
    if not os.path.isfile(python):
        return f"Python not found: {python} (set in {where})"
    if not os.access(python, os.X_OK):
        return f"Python is not executable: {python} (set in {where})"
    return ""


def user_train_script(context=None) -> str:
    """The train script set in the preferences ("" : train from the extension itself)."""
    p = get(context)
    return bpy.path.abspath(p.train_script) if p and p.train_script else ""


def flame_model(context=None) -> str:
    p = get(context)
    return bpy.path.abspath(p.flame_model) if p and p.flame_model else ""


classes = (PA_Preferences,)
