"""Thin bpy layer: operators, panels, properties, preview. Maths lives in core/."""

# The extension's top package ("bl_ext.<repo>.progressive_avatars" when installed,
# "progressive_avatars" from a checkout): add-on preferences are keyed by it.
ADDON_PACKAGE = __package__.rpartition(".")[0] or __package__


def _load():
    from . import handlers, operators_avatar, operators_import, operators_train, panels, prefs, properties

    return handlers, operators_avatar, operators_import, operators_train, panels, prefs, properties


def _extra_classes():
    # Modules added for issue 19 (splat look, non-blocking render, PLY import).
    from . import ply_import, render_job, splat_look  # noqa: F401 (render_job: no classes)

    return (*splat_look.classes, *ply_import.classes)


def _classes():
    _, ops_avatar, ops_import, ops_train, panels, prefs, properties = _load()
    return (
        *properties.classes,
        *prefs.classes,
        *ops_import.classes,
        *ops_avatar.classes,
        *ops_train.classes,
        *_extra_classes(),
        *panels.classes,
    )


def register():
    import bpy

    handlers, _, ops_import, _, _, _, properties = _load()
    for cls in _classes():
        bpy.utils.register_class(cls)
    properties.register_props()
    bpy.types.TOPBAR_MT_file_import.append(ops_import.menu_import)
    from . import ply_import

    bpy.types.TOPBAR_MT_file_import.append(ply_import.menu_import)
    handlers.register()


def unregister():
    import bpy

    handlers, _, ops_import, _, _, _, properties = _load()
    handlers.unregister()
    bpy.types.TOPBAR_MT_file_import.remove(ops_import.menu_import)
    from . import ply_import

    bpy.types.TOPBAR_MT_file_import.remove(ply_import.menu_import)
    properties.unregister_props()
    for cls in reversed(_classes()):
        bpy.utils.unregister_class(cls)
    from . import operators_train, render_job, runtime

    runtime.forget()
    render_job.stop_all()
    operators_train.stop_all("the extension was disabled")
