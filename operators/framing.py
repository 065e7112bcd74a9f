"""Frame Volume (a camera showing the whole volume from a side) and Hide Enclosing Objects
(the objects that hide the volume, e.g. the default cube): :mod:`..blender.framing`."""

import bpy
from bpy.props import EnumProperty

from ..blender import framing, jobs
from ..blender.objects import active_volume, poll_volume

SIDE_ITEMS = tuple((side, side.title(), f"Look at the volume from the {side.lower()}, as the "
                    f"3D view's {side.title()} view") for side in framing.SIDES)


class VOLUMEEVM_OT_frame_volume(bpy.types.Operator):
    """Place the scene camera (made if there is none) so the whole volume is in view from the
    chosen side, with its clip range around the volume"""

    bl_idname = "volumeevm.frame_volume"
    bl_label = "Frame Volume"
    bl_options = {"REGISTER", "UNDO"}

    side: EnumProperty(name="Side", items=SIDE_ITEMS, default="FRONT")

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=False) is not None

    def execute(self, context):
        try:
            camera = framing.frame_volume(active_volume(context), self.side, scene=context.scene)
        except jobs.REPORTED_ERRORS as error:
            return jobs.report_failure(self, error)
        self.report({"INFO"}, f"{camera.name} frames the volume from the {self.side.lower()}")
        return {"FINISHED"}


class VOLUMEEVM_OT_hide_enclosing(bpy.types.Operator):
    """Hide the objects that enclose the volume (e.g. the default cube), in the viewport and
    the render: they would hide it"""

    bl_idname = "volumeevm.hide_enclosing"
    bl_label = "Hide Enclosing Objects"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=False) is not None

    def execute(self, context):
        hidden = framing.hide_enclosing(active_volume(context), context.scene)
        self.report({"INFO"}, f"Hid {', '.join(o.name for o in hidden) or 'nothing'}")
        return {"FINISHED"}


CLASSES = [VOLUMEEVM_OT_frame_volume, VOLUMEEVM_OT_hide_enclosing]
