"""Build the VolumeEVM of the active volume at a threshold (data units)."""

import bpy
from bpy.props import BoolProperty, FloatProperty

from . import _jobs, api


def poll_volume(cls, context, *, built):
    """The volume an operator acts on (``built``: with its VolumeEVM), or None with the poll
    message saying why the button is disabled."""
    obj = active_volume(context)
    if obj is None:
        cls.poll_message_set("Select a volume object (File > Import > Volume (VolumeEVM))")
        return None
    if built and not obj.volumeevm.vevm_path:
        cls.poll_message_set("No VolumeEVM built yet: build one first")
        return None
    if _jobs.CURRENT is not None:
        cls.poll_message_set(f"Busy: {_jobs.CURRENT.label}")
        return None
    return obj


def active_volume(context):
    """The volume object of the active object, or None."""
    obj = context.active_object
    if obj is None:
        return None
    s = obj.volumeevm
    if s.role == "VOLUME":
        return obj
    if s.role == "SURFACE" and s.volume is not None:
        return s.volume
    return None


class VOLUMEEVM_OT_build_vevm(_jobs.JobOperator, bpy.types.Operator):
    """Build the VolumeEVM (extreme vertices + densities) of the voxels whose density is at
    least the threshold (and at most the upper bound), and keep it beside the .blend"""

    bl_idname = "volumeevm.build_vevm"
    bl_label = "Build VolumeEVM"
    bl_options = {"REGISTER", "UNDO"}

    use_settings: BoolProperty(
        name="Use Object Settings", default=True,
        description="Take threshold and upper bound from the volume object's settings",
        options={"SKIP_SAVE"})
    threshold: FloatProperty(name="Threshold", description="Lower bound (data units)",
                             options={"SKIP_SAVE"})
    use_upper: BoolProperty(name="Upper Bound", options={"SKIP_SAVE"})
    upper: FloatProperty(name="Upper", description="Upper bound (data units)",
                         options={"SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=False) is not None

    def job(self, context):
        obj = active_volume(context)
        if self.use_settings:
            return api.build_job(obj)
        return api.build_job(obj, self.threshold, self.upper if self.use_upper else None)

    def finished(self, context, vevm):
        r = vevm.size_report()
        self.report({"INFO"}, f"VolumeEVM: {vevm.voxel_count} voxels, {len(vevm.evm)} extreme "
                              f"vertices, {100 * r['ratio']:.1f}% of the dense size")


CLASSES = [VOLUMEEVM_OT_build_vevm]
