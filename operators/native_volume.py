"""Make the region a native Blender Volume object (an OpenVDB grid) for Cycles and EEVEE."""

import bpy

from ..blender import jobs, native_volume, runtime
from ..blender.objects import active_volume, poll_volume


class VOLUMEEVM_OT_make_volume_object(bpy.types.Operator):
    """Make (or refresh) a Blender Volume object of the region (sparse OpenVDB grid beside the
    .blend) with a material from the transfer function, so Cycles and EEVEE render it too"""

    bl_idname = "volumeevm.make_volume_object"
    bl_label = "Make Volume Object"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=True) is not None

    def execute(self, context):
        vol_obj = active_volume(context)
        try:
            native = native_volume.make_volume_object(vol_obj, scene=context.scene)
        except jobs.REPORTED_ERRORS as error:
            return jobs.report_failure(self, error)
        note = runtime.status(vol_obj.volumeevm.uid)
        if note:
            self.report({"WARNING"}, note)
        else:
            timing = native_volume.last_timing(vol_obj)
            self.report({"INFO"}, f"{native.name}: {timing['voxels']:,} voxels, "
                                  f"{timing['file_bytes'] / 1e6:.1f} MB grid file")
        return {"FINISHED"}


CLASSES = [VOLUMEEVM_OT_make_volume_object]
