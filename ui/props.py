"""Settings stored in the .blend: ``Scene.volumeevm`` and ``Object.volumeevm``.

Only small values live here (sizes, spacing, thresholds, counts, a 32-bin histogram, paths).
Bulk data never goes into ID properties: the dense volume stays in a runtime cache in Python
(``operators/_runtime.py``) and the VolumeEVM in a ``.vevm`` sidecar file beside the .blend
(``operators/sidecar.py``).
"""

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    PointerProperty,
    StringProperty,
)

from ..operators import api
from ..operators.api import HISTOGRAM_BINS


class VolumeEVMSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide VolumeEVM settings (``Scene.volumeevm``)."""

    histogram_log: BoolProperty(
        name="Log Scale",
        description="Draw histogram bars on a logarithmic scale (CT is mostly air)",
        default=True,
    )


#: Tool operations of the stack: (identifier, name, description).
TOOL_OPERATIONS = (
    ("CUT", "Cut", "Remove the material inside the tool"),
    ("KEEP", "Keep Inside", "Keep only the material inside the tool"),
    ("ADD", "Add", "Add the tool's inside as material with a density"),
    ("LARGEST", "Keep Largest Part", "Keep only the largest face-connected part"),
    ("CLIP", "Clip to Box", "Keep only the material inside the tool's bounding box"),
)


def is_mesh_object(settings, obj):
    """Pointer poll of stack entries: mesh objects that are not VolumeEVM volumes."""
    return obj.type == "MESH" and obj.volumeevm.role != "VOLUME"


def _entry_changed(entry, context):
    api.entry_changed(entry.id_data)


class VolumeEVMToolEntry(bpy.types.PropertyGroup):
    """One entry of a volume's tool stack (``Object.volumeevm.tools``).

    Changing a field (in the sidebar or from a script) re-evaluates the stack at once.
    """

    tool: PointerProperty(
        name="Tool", type=bpy.types.Object, poll=is_mesh_object,
        description="The closed mesh object that cuts, keeps or adds material",
        update=_entry_changed,
    )
    operation: EnumProperty(name="Operation", items=TOOL_OPERATIONS, default="CUT",
                            update=_entry_changed)
    enabled: BoolProperty(name="Enabled", default=True, update=_entry_changed,
                          description="Apply this entry (disabled entries are skipped)")
    use_density: BoolProperty(
        name="Own Density", default=False, update=_entry_changed,
        description="Give added voxels this density; off: the region's largest density",
    )
    density: FloatProperty(name="Density", precision=3, update=_entry_changed,
                           description="Density of added voxels, in data units")


class VolumeEVMObjectSettings(bpy.types.PropertyGroup):
    """Per-object VolumeEVM state (``Object.volumeevm``).

    A *volume* object is the wire box of an imported grid; it holds where the data came from,
    the grid geometry, the threshold and the sidecar of its VolumeEVM. A *surface* object is
    the mesh of the VolumeEVM's boundary, parented to its volume object.
    """

    role: EnumProperty(
        name="Role",
        items=(
            ("NONE", "None", "Not a VolumeEVM object"),
            ("VOLUME", "Volume", "The box of an imported volume"),
            ("SURFACE", "Surface", "The boundary mesh of a VolumeEVM"),
        ),
        default="NONE",
    )
    uid: StringProperty(
        name="Volume ID",
        description="Key of the dense volume in the runtime cache (not saved data)",
    )
    # --- where the volume came from
    source_path: StringProperty(
        name="Source",
        description="File or DICOM folder the volume was read from; Build re-reads it when "
                    "the volume is no longer in memory",
        subtype="FILE_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
    )
    reader_options: StringProperty(
        name="Reader Options",
        description="Options the reader was given (JSON), used again when re-reading",
        default="{}",
    )
    # --- grid geometry and data (small values only)
    shape: IntVectorProperty(name="Size", size=3, min=0, description="Voxels along x, y, z")
    spacing: FloatVectorProperty(name="Spacing", size=3, default=(1.0, 1.0, 1.0),
                                 description="Voxel size in mm along x, y, z")
    origin: FloatVectorProperty(name="Origin", size=3,
                                description="Centre of voxel (0, 0, 0) in mm (LPS)")
    orientation: FloatVectorProperty(name="Orientation", size=9,
                                     default=(1, 0, 0, 0, 1, 0, 0, 0, 1),
                                     description="Index axis directions in LPS (3x3, row-major)")
    spacing_known: BoolProperty(name="Spacing Known", default=True)
    units: StringProperty(name="Units", description="The data's own units (e.g. HU)")
    dtype: StringProperty(name="Data Type")
    value_min: FloatProperty(name="Minimum", description="Smallest density (data units)")
    value_max: FloatProperty(name="Maximum", description="Largest density (data units)")
    histogram: FloatVectorProperty(
        name="Histogram", size=HISTOGRAM_BINS,
        description="Voxel counts in equal bins from the minimum to the maximum density",
    )
    # --- the region of interest
    threshold: FloatProperty(
        name="Threshold",
        description="Lower bound of the region, in the data's own units (voxels with density "
                    ">= threshold are in the region)",
        default=0.0,
        precision=3,
    )
    use_upper: BoolProperty(
        name="Upper Bound",
        description="Also leave out voxels denser than the upper bound",
        default=False,
    )
    upper: FloatProperty(
        name="Upper",
        description="Upper bound of the region, in data units (density <= upper)",
        default=0.0,
        precision=3,
    )
    # --- the VolumeEVM built last (its sidecar file and what it holds)
    vevm_path: StringProperty(
        name="Sidecar",
        description="The .vevm file holding the VolumeEVM ('//' = beside the .blend)",
        subtype="FILE_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
    )
    built_threshold: FloatProperty(name="Built Threshold", precision=3)
    built_use_upper: BoolProperty(name="Built With Upper Bound")
    built_upper: FloatProperty(name="Built Upper", precision=3)
    voxel_count: IntProperty(name="Voxels", description="Voxels in the region", min=0)
    ev_count: IntProperty(name="Extreme Vertices", min=0)
    vevm_bytes: FloatProperty(name="VolumeEVM Bytes", description="Vertices + densities table")
    dense_bytes: FloatProperty(name="Dense Bytes", description="The dense array")
    # --- the non-destructive tool stack (evaluated on top of the VolumeEVM above)
    tools: CollectionProperty(name="Tools", type=VolumeEVMToolEntry,
                              description="Tool operations applied in order to the VolumeEVM")
    tool_index: IntProperty(name="Active Tool Entry", min=0)
    tool_object: PointerProperty(
        name="Tool", type=bpy.types.Object,
        description="The object the tool buttons use: any closed mesh (the buttons say why "
                    "another object cannot be used)",
    )
    tool_use_density: BoolProperty(
        name="Own Density", default=False,
        description="Add with this density; off: the region's largest density",
    )
    tool_density: FloatProperty(name="Density", precision=3,
                                description="Density of added material, in data units")
    # --- links between a volume and its surface
    surface: PointerProperty(name="Surface", type=bpy.types.Object,
                             description="The mesh made from this volume's VolumeEVM")
    volume: PointerProperty(name="Volume", type=bpy.types.Object,
                            description="The volume object this surface was made from")
    stack_signature: StringProperty(
        name="Stack Signature",
        description="Digest of the VolumeEVM and tool stack this surface mesh shows ('' = the "
                    "VolumeEVM itself); undo restores it with the mesh",
    )


CLASSES = [VolumeEVMSceneSettings, VolumeEVMToolEntry, VolumeEVMObjectSettings]
