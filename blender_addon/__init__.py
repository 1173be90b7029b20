"""Thin bpy layer: operators, panels, properties. Maths lives in core/."""


def register():
    pass


def unregister():
    pass
