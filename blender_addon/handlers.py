"""Keep previews in step with their meshes: new frame, mesh edits, file loads."""

import os

import bpy
from bpy.app.handlers import persistent

from . import runtime

_busy = False  # our own writes to preview meshes re-enter depsgraph_update_post


def _update_scene(scene, depsgraph, only_sources=None):
    global _busy
    if _busy:
        return
    _busy = True
    try:
        for obj in runtime.previews(scene):
            src = runtime.bound_mesh(obj)
            if only_sources is not None and (src is None or src.original not in only_sources):
                continue
            try:
                if src is None:  # its mesh was deleted: refresh says so, and shows only points it placed
                    runtime.refresh(obj, depsgraph)
                    continue
                e = runtime.entry(obj)
                if e is None:
                    continue
                count = e.budget.count_for_slider(obj.pa_avatar.budget)
                if count != obj.pa_avatar.count:  # an animated budget moves without the update callback
                    runtime.apply_budget(obj, depsgraph=depsgraph)
                elif e.depth_failed:  # not written while the mesh was in Edit Mode; refresh clears the status
                    runtime.write_depth(obj, e, count)
                runtime.refresh(obj, depsgraph, count)
            except Exception as exc:  # a handler must never break playback
                obj.pa_avatar.status = f"Preview update failed: {exc}"
    finally:
        _busy = False


@persistent
def on_frame_change(scene, depsgraph):
    _update_scene(scene, depsgraph)


@persistent
def on_depsgraph_update(scene, depsgraph):
    if _busy:
        return
    changed, moved = set(), set()
    for upd in depsgraph.updates:
        if isinstance(upd.id, bpy.types.Object):
            if upd.is_updated_geometry:
                changed.add(upd.id.original)
            if upd.is_updated_transform:
                moved.add(upd.id.original)
    if not changed and not moved:
        return
    bound = [(o, runtime.bound_mesh(o)) for o in runtime.previews(scene)]
    sources = {src for _, src in bound} & changed
    for obj, src in bound:
        if src is None:
            continue
        e = runtime.cached(obj)
        # A preview left Edit Mode: its points are the ones it entered with, whatever frame it is now.
        if e is not None and obj.original in changed and not obj.data.is_editmode and e.frame_key is None:
            sources.add(src)
        # It or its mesh moved, or it was re-parented: whether it still draws on the mesh, said at
        # once (a preview not parented to its mesh stays put when the mesh moves), decoded avatar
        # or not (none yet after a file load).
        if obj.original in moved or src in moved:
            try:
                runtime.placement_status(obj, depsgraph)
            except Exception as exc:  # a handler must never break an edit
                obj.pa_avatar.status = f"Preview update failed: {exc}"
    if sources:
        _update_scene(scene, depsgraph, sources)


@persistent
def on_load_pre(*_args):
    # No training carries over into another file: its trainer would run on unread.
    from . import operators_train

    operators_train.stop_all()


@persistent
def on_load_post(*_args):
    # Caches describe objects of the previous file; they reload lazily from stored paths.
    runtime.forget()
    from . import depth, operators_train

    operators_train.clear_after_load()  # a file saved mid-training stored "running"
    depth.after_load()


_relocated = []  # (object, previous path) while a save is under way


@persistent
def on_save_pre(filepath, *_args):
    """Store avatar paths relative to the .blend being written ("//..."), as Blender does for
    its own file paths when Relative Paths is on, so a moved project keeps its avatars. Paths
    relative already follow the file into another folder whatever the preference, as Save As
    remaps Blender's own."""
    _relocated.clear()
    if not filepath:
        return
    relative = bpy.context.preferences.filepaths.use_relative_paths
    start = os.path.dirname(os.path.abspath(filepath))
    for obj in bpy.data.objects:
        st = obj.pa_avatar
        # Linked and overridden previews keep paths relative to their library, as Blender does.
        if not st.is_preview or not st.filepath or runtime.path_library(obj) is not None:
            continue
        if not relative and not st.filepath.startswith("//"):
            continue
        path = runtime.avatar_path(obj)
        if os.path.isfile(path):
            st.filepath_absolute = path
        try:
            rel = "//" + os.path.relpath(path, start).replace(os.sep, "/")
        except ValueError:  # another drive
            continue
        if rel != st.filepath:
            _relocated.append((obj, st.filepath))
            st.filepath = rel


def _put_back():
    for obj, old in _relocated:
        try:
            obj.pa_avatar.filepath = old
        except ReferenceError:
            pass
    _relocated.clear()


@persistent
def on_save_post(filepath="", *_args):
    # Save Copy wrote another file and this one stays open: its paths stay relative to this one.
    if filepath and os.path.normcase(os.path.abspath(filepath)) != os.path.normcase(os.path.abspath(bpy.data.filepath)):
        _put_back()
    _relocated.clear()


@persistent
def on_save_fail(*_args):
    _put_back()  # the file was not written: paths stay relative to the old one


@persistent
def on_undo_redo(*_args):
    # Undo restores preview attributes as they were at that step; points the cache counted
    # as evaluated since may hold another frame's positions, so nothing is trusted past it.
    runtime.invalidate()
    # Undo takes back properties but not what lives outside the file's data: a training in
    # progress, the 3D views' colour mode that depth colours set.
    from . import depth, operators_train

    operators_train.restore_runs()
    depth.sync_views()


@persistent
def on_blend_import(context):
    """Appended previews: their "//" avatar path was relative to the .blend they came from;
    rebase it here, as Blender rebases its own paths on append (files saved before
    filepath_absolute existed have nothing else to find their avatar by)."""
    from .operators_avatar import stored_path

    for item in context.import_items:
        obj, lib = item.id, item.source_library
        if item.append_action not in ("MAKE_LOCAL", "COPY_LOCAL") or not isinstance(obj, bpy.types.Object):
            continue
        st = obj.pa_avatar
        if st.is_preview and st.filepath.startswith("//") and lib is not None:
            path = runtime.resolve(st.filepath, lib)
            st.filepath, st.filepath_absolute = stored_path(path), path


@persistent
def on_render_pre(scene, *_args):
    """The splats' dilation needs the focal length of the camera and resolution rendered now."""
    from . import splat_look

    try:
        warning = splat_look.focal_warning(scene)
    except Exception as exc:  # a handler must never stop a render
        warning = f"Splat focal length not set: {exc}"
    if warning:
        print(f"Progressive Avatars: {warning}")


_HANDLERS = (
    (bpy.app.handlers.undo_post, on_undo_redo),
    (bpy.app.handlers.redo_post, on_undo_redo),
    (bpy.app.handlers.frame_change_post, on_frame_change),
    (bpy.app.handlers.render_pre, on_render_pre),
    (bpy.app.handlers.depsgraph_update_post, on_depsgraph_update),
    (bpy.app.handlers.load_pre, on_load_pre),
    (bpy.app.handlers.load_post, on_load_post),
    (bpy.app.handlers.save_pre, on_save_pre),
    (bpy.app.handlers.save_post, on_save_post),
)
_HANDLERS += ((bpy.app.handlers.save_post_fail, on_save_fail),) if hasattr(bpy.app.handlers, "save_post_fail") else ()
_HANDLERS += (
    ((bpy.app.handlers.blend_import_post, on_blend_import),) if hasattr(bpy.app.handlers, "blend_import_post") else ()
)


def register():
    for lst, fn in _HANDLERS:
        if fn not in lst:
            lst.append(fn)


def unregister():
    for lst, fn in _HANDLERS:
        while fn in lst:
            lst.remove(fn)
