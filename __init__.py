"""ProgressiveAvatars Blender extension entry point.

Only register()/unregister() live here. bpy is imported lazily so that
``progressive_avatars.core`` stays importable outside Blender.
"""


def register():
    from .blender_addon import register as _register

    _register()


def unregister():
    from .blender_addon import unregister as _unregister

    _unregister()
