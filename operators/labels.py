"""Label maps: make their labels mesh objects (one per label, named and coloured from the file),
measure them for the sidebar's list, export the measurements as CSV."""

import bpy
from bpy_extras.io_utils import ExportHelper

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
        return labels.label_meshes_job(context, active_volume(context),
                                       single_mesh=self.single_mesh, manifold=self.manifold)

    def finished(self, context, made):
        faces = sum(len(obj.data.polygons) for obj in made)
        self.report({"INFO"}, f"{len(made)} label mesh object(s), {faces} faces")


class VOLUMEEVM_OT_measure_labels(jobs.JobOperator, bpy.types.Operator):
    """Measure every label of the active volume's label map exactly (volume, boundary area,
    parts) and list them in the sidebar"""

    bl_idname = "volumeevm.measure_labels"
    bl_label = "Measure Labels"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=False) is not None

    def job(self, context):
        return labels.measure_job(context, active_volume(context))

    def finished(self, context, rows):
        self.report({"INFO"}, f"{len(rows)} label(s) measured")


class VOLUMEEVM_OT_export_label_measurements(ExportHelper, jobs.JobOperator, bpy.types.Operator):
    """Write every label's exact measurements (volume, area, box, centroid, parts) as CSV"""

    bl_idname = "volumeevm.export_label_measurements"
    bl_label = "Export Measurements (CSV)"
    bl_options = {"REGISTER"}

    filename_ext = ".csv"
    filter_glob: bpy.props.StringProperty(default="*.csv", options={"HIDDEN"})
    overwrite: bpy.props.BoolProperty(
        name="Overwrite", default=False,
        description="Replace the file if it exists (off: an existing file is refused)")

    @classmethod
    def poll(cls, context):
        return poll_volume(cls, context, built=False) is not None

    def job(self, context):
        return labels.export_measurements_job(context, active_volume(context), self.filepath,
                                              overwrite=self.overwrite)

    def finished(self, context, written):
        self.report({"INFO"}, f"Measurements written to {written}")


CLASSES = [VOLUMEEVM_OT_make_label_meshes, VOLUMEEVM_OT_measure_labels,
           VOLUMEEVM_OT_export_label_measurements]
