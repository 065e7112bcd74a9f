"""Make a label map's labels mesh objects: one per label, named and coloured from the file."""

import bpy

from ..blender import jobs, labels
from ..blender.objects import active_volume, poll_volume


class VOLUMEEVM_OT_make_label_meshes(jobs.JobOperator, bpy.types.Operator):
    """Make every label of the active volume's label map (a segmentation) an exact mesh:
    one object per label, named and coloured from the file, sharing faces where labels touch"""

    bl_idname = "volumeevm.make_label_meshes"
    bl_label = "Make Label Meshes"
    bl_options = {"REGISTER", "UNDO"}

    single_mesh: bpy.props.BoolProperty(
        name="One Mesh",
        description="One mesh object with a material per label and the face attribute 'label', "
                    "instead of one object per label",
        default=False,
    )

    manifold: bpy.props.BoolProperty(
        name="Manifold (for 3D printing)",
        description="Split the edges and points where voxels touch only there, so each label's "
                    "mesh is 2-manifold (see Make Manifold Mesh)",
        default=False,
    )

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=False) is not None

    def job(self, context):
        return labels.label_meshes_job(context, active_volume(context), single_mesh=self.single_mesh,
                                         manifold=self.manifold)

    def finished(self, context, made):
        faces = sum(len(obj.data.polygons) for obj in made)
        self.report({"INFO"}, f"{len(made)} label mesh object(s), {faces} faces")


CLASSES = [VOLUMEEVM_OT_make_label_meshes]
