"""Build the VolumeEVM of the active volume at a threshold (data units)."""

import bpy
from bpy.props import BoolProperty, FloatProperty

from ..blender import jobs, volumes
from ..blender.objects import active_volume, poll_volume


class VOLUMEEVM_OT_build_vevm(jobs.JobOperator, bpy.types.Operator):
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
            return volumes.build_job(obj)
        return volumes.build_job(obj, self.threshold, self.upper if self.use_upper else None)

    def finished(self, context, vevm):
        r = vevm.size_report()
        self.report({"INFO"}, f"VolumeEVM: {vevm.voxel_count} voxels, {len(vevm.evm)} extreme "
                              f"vertices, {100 * r['ratio']:.1f}% of the dense size")


CLASSES = [VOLUMEEVM_OT_build_vevm]
