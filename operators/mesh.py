"""Make the VolumeEVM's boundary a mesh object at physical size and position."""

import bpy

from ..blender import jobs, volumes
from ..blender.objects import active_volume, poll_volume


class VOLUMEEVM_OT_make_mesh(jobs.JobOperator, bpy.types.Operator):
    """Make (or refresh) the surface mesh of the active volume's VolumeEVM: exact voxel
    boundary, merged rectangles, in millimetres (1 mm = 0.001 units)"""

    bl_idname = "volumeevm.make_mesh"
    bl_label = "Make Mesh"
    bl_options = {"REGISTER", "UNDO"}

    manifold: bpy.props.BoolProperty(
        name="Manifold (for 3D printing)",
        description="Split the edges and vertices where voxels touch only along an edge or at "
                    "a point (copies 0.001 voxel apart), so that every edge has two faces",
        default=False)
    smooth: bpy.props.BoolProperty(
        name="Smooth (display)",
        description="Relax the vertices into a smooth surface, each within half a voxel of the "
                    "exact boundary, shaded smooth; tools and measurements keep the exact mesh",
        default=False)

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=True) is not None

    def job(self, context):
        return volumes.mesh_job(context, active_volume(context), self.manifold, self.smooth)

    def finished(self, context, surface):
        mesh = surface.data
        self.report({"INFO"}, f"{surface.name}: {len(mesh.vertices)} vertices, "
                              f"{len(mesh.polygons)} polygons")


CLASSES = [VOLUMEEVM_OT_make_mesh]
