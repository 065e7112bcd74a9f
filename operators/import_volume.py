"""File > Import > Volume (VolumeEVM), the sidebar's Import button and drag-and-drop."""

import os

import bpy
from bpy.props import (
    CollectionProperty,
    EnumProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    StringProperty,
)
from bpy_extras.io_utils import ImportHelper

from ..blender import framing, jobs, volumes
from ..volumeevm_addon.readers import SUPPORTED_EXTENSIONS

_RAW_ENDINGS = (".raw", ".bin")


def _is_raw(path):
    return str(path).lower().endswith(_RAW_ENDINGS)


class VOLUMEEVM_OT_import_volume(jobs.JobOperator, bpy.types.Operator, ImportHelper):
    """Import a volume (NumPy, raw, NRRD, NIfTI, DICOM series, TIFF stack, VolPack .den,
    OME-Zarr store) as a VolumeEVM volume object. For DICOM pick one file of the series or the
    folder; for OME-Zarr open the store's folder (or pick any file in it)"""

    bl_idname = "volumeevm.import_volume"
    bl_label = "Import Volume"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ""
    filter_glob: StringProperty(
        default=";".join(f"*{e}" for e in SUPPORTED_EXTENSIONS),
        options={"HIDDEN"},
    )
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement,
                              options={"HIDDEN", "SKIP_SAVE"})
    name: StringProperty(name="Name", description="Object name (default: the file's name)")
    units: StringProperty(name="Units", description="The data's units, e.g. HU (empty: as the "
                                                    "file says)")
    read_as: EnumProperty(
        name="Read As",
        items=(("AUTO", "Automatic", "As the file says (a 3D Slicer .seg.nrrd is a label map, "
                                     "other files densities)"),
               ("DENSITIES", "Densities", "Values are densities (CT, MRI, microscopy)"),
               ("LABELS", "Label Map", "A segmentation: every integer value >= 1 is a label, "
                                       "0 the background")),
        default="AUTO", options={"SKIP_SAVE"},  # each import starts from what the file says
        description="Whether the file holds densities or a label map (segmentation)")
    label_table: StringProperty(
        name="Label Table", subtype="FILE_PATH", options={"SKIP_SAVE"},
        description="Label Map: the labels' names and colours, an ITK-SNAP label description "
                    "(.txt) or JSON {label: {name, color}} (empty: a fixed palette)")
    raw_shape: IntVectorProperty(
        name="Raw Size", size=3, min=0, default=(0, 0, 0),
        description="Raw files: voxels along x, y, z (x fastest in the file)")
    raw_dtype: EnumProperty(
        name="Raw Type",
        items=[(t, t, f"{t} samples") for t in
               ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")],
        default="uint16",
        description="Raw files: sample type")
    raw_byte_order: EnumProperty(
        name="Byte Order",
        items=(("little", "Little Endian", ""), ("big", "Big Endian", "")),
        default="little")
    raw_header_bytes: IntProperty(name="Header Bytes", min=0, default=0,
                                  description="Raw files: bytes to skip before the samples")
    raw_spacing: FloatVectorProperty(name="Raw Spacing", size=3, min=0.0, default=(1.0, 1.0, 1.0),
                                     description="Raw files: voxel size in mm")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "name")
        layout.prop(self, "units")
        layout.prop(self, "read_as")
        if self.read_as == "LABELS":
            layout.prop(self, "label_table")
        header, body = layout.panel("VOLUMEEVM_import_raw", default_closed=True)
        header.label(text="Raw Files")
        if body:
            for prop in ("raw_shape", "raw_dtype", "raw_byte_order", "raw_header_bytes",
                         "raw_spacing"):
                body.prop(self, prop)

    def _source(self):
        """The path (or list of DICOM files, or the OME-Zarr store) the user picked."""
        names = [f.name for f in self.files if f.name]
        store = volumes.zarr_store(self.filepath or self.directory)
        if store is not None:
            return str(store)
        if self.directory and len(names) > 1:
            return [os.path.join(self.directory, n) for n in names]
        if self.filepath and not os.path.isdir(self.filepath):
            return self.filepath
        if self.directory:
            return self.directory
        return self.filepath

    def _options(self, source):
        options = {}
        if self.read_as == "DENSITIES":
            options["labels"] = False
        elif self.read_as == "LABELS":
            options["labels"] = bpy.path.abspath(self.label_table) if self.label_table else True
        if isinstance(source, str) and _is_raw(source):
            options.update(shape=tuple(self.raw_shape), dtype=self.raw_dtype,
                           byte_order=self.raw_byte_order, header_bytes=self.raw_header_bytes,
                           spacing=tuple(self.raw_spacing))
        return options

    def job(self, context):
        source = self._source()
        if not source:
            raise OSError("no file or folder chosen")
        return volumes.import_job(context, source, name=self.name or None,
                                  units=self.units or None, **self._options(source))

    def finished(self, context, obj):
        s = obj.volumeevm
        what = (f"{s.label_count} labels" if s.label_count
                else f"values {s.value_min:g} .. {s.value_max:g} {s.units}")
        self.report({"INFO"}, f"Imported {obj.name}: {tuple(s.shape)} voxels, {what}")
        enclosing = framing.enclosing_objects(obj, context.scene)
        if enclosing:
            self.report({"WARNING"}, f"{', '.join(o.name for o in enclosing)} enclose(s) the "
                                     f"volume and hide it: Hide Enclosing Objects (Volume panel)")

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        if self.directory:
            # Drag-and-drop (``directory`` is never remembered between calls). Raw files need
            # their options first.
            if _is_raw(self.filepath):
                return self.invoke_popup(context)
            return self.execute(context)
        return ImportHelper.invoke(self, context, event)


class VOLUMEEVM_FH_import_volume(bpy.types.FileHandler):
    """Drop a volume file on the 3D view to import it."""

    bl_idname = "VOLUMEEVM_FH_import_volume"
    bl_label = "Volume (VolumeEVM)"
    bl_import_operator = "volumeevm.import_volume"
    bl_file_extensions = ";".join(SUPPORTED_EXTENSIONS)

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


def menu_import(self, context):
    """File > Import entry."""
    self.layout.operator(VOLUMEEVM_OT_import_volume.bl_idname, text="Volume (VolumeEVM)")


CLASSES = [VOLUMEEVM_OT_import_volume, VOLUMEEVM_FH_import_volume]
