"""Settings stored in the .blend: ``Scene.volumeevm`` and ``Object.volumeevm``.

Only small values live here (sizes, spacing, thresholds, counts, a 32-bin histogram, paths).
Bulk data never goes into ID properties: the dense volume stays in a runtime cache in Python
(``operators/_runtime.py``) and the VolumeEVM in a ``.vevm`` sidecar file beside the .blend
(``operators/sidecar.py``).
"""

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    PointerProperty,
    StringProperty,
)

from ..operators.api import HISTOGRAM_BINS


class VolumeEVMSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide VolumeEVM settings (``Scene.volumeevm``)."""

    histogram_log: BoolProperty(
        name="Log Scale",
        description="Draw histogram bars on a logarithmic scale (CT is mostly air)",
        default=True,
    )


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
    # --- links between a volume and its surface
    surface: PointerProperty(name="Surface", type=bpy.types.Object,
                             description="The mesh made from this volume's VolumeEVM")
    volume: PointerProperty(name="Volume", type=bpy.types.Object,
                            description="The volume object this surface was made from")


CLASSES = [VolumeEVMSceneSettings, VolumeEVMObjectSettings]
