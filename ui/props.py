"""Settings stored in the .blend: ``Scene.volumeevm``, ``Scene.volumeevm_render`` and
``Object.volumeevm``.

Only small values live here (sizes, spacing, thresholds, counts, a 32-bin histogram, paths,
render settings). Bulk data never goes into ID properties: the dense volume stays in a runtime
cache in Python (``blender/runtime.py``) and the VolumeEVM in a ``.vevm`` sidecar file beside
the .blend (``blender/sidecar.py``).

The enums' identifiers come from one place each: the core's method records
(``volumeevm_addon.rendering.methods()``: identifier, name and description), the core's
``MODES``, ``LEVELS`` and ``PRESETS``, the tool stack's ``TOOL_KINDS`` (only shear-warp's two
classifications are listed here); the other names and descriptions shown in the sidebar are
written here.
"""

import json

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

from ..blender import gpu_viewport, tool_stack
from ..blender.dvr import DEFAULT_IMAGE
from ..blender.labels import select_label
from ..blender.objects import render_volume
from ..blender.transfer import load_preset
from ..blender.volumes import HISTOGRAM_BINS
from ..volumeevm_addon import LEVELS, MODES, PRESETS
from ..volumeevm_addon.rendering import methods


def enum_items(names, texts):
    """Blender enum items for the core's ``names``, with the sidebar's ``texts``
    (``{name: (label, description)}``, in the order the sidebar lists them).

    Raises
    ------
    RuntimeError
        If ``texts`` does not name exactly ``names`` (the core added or dropped one).
    """
    if set(names) != set(texts):
        raise RuntimeError(f"enum texts {sorted(texts)} do not match the names {sorted(names)}")
    return tuple((name, *texts[name]) for name in texts)


class VolumeEVMSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide VolumeEVM settings (``Scene.volumeevm``)."""

    histogram_log: BoolProperty(
        name="Log Scale",
        description="Draw histogram bars on a logarithmic scale (CT is mostly air)",
        default=True,
    )


#: Tool operations of the stack: (identifier, name, description).
TOOL_OPERATION_ITEMS = tuple((kind.identifier, kind.label, kind.description)
                             for kind in tool_stack.TOOL_KINDS)


def is_mesh_object(settings, obj):
    """Pointer poll of stack entries: mesh objects that are not VolumeEVM volumes."""
    return obj.type == "MESH" and obj.volumeevm.role != "VOLUME"


def _entry_changed(entry, context):
    tool_stack.entry_changed(entry.id_data)


class VolumeEVMToolEntry(bpy.types.PropertyGroup):
    """One entry of a volume's tool stack (``Object.volumeevm.tools``).

    Changing a field (in the sidebar or from a script) marks the stack for a refresh
    (:func:`..blender.tool_stack.entry_changed`).
    """

    tool: PointerProperty(
        name="Tool", type=bpy.types.Object, poll=is_mesh_object,
        description="The closed mesh object that cuts, keeps or adds material",
        update=_entry_changed,
    )
    operation: EnumProperty(name="Operation", items=TOOL_OPERATION_ITEMS, default="CUT",
                            update=_entry_changed)
    enabled: BoolProperty(name="Enabled", default=True, update=_entry_changed,
                          description="Apply this entry (disabled entries are skipped)")
    use_density: BoolProperty(
        name="Own Density", default=False, update=_entry_changed,
        description="Give added voxels this density; off: the region's largest density",
    )
    density: FloatProperty(name="Density", precision=3, update=_entry_changed,
                           description="Density of added voxels, in data units")
    label: IntProperty(name="Label", min=0, update=_entry_changed,
                       description="Add on a label map's label objects: the label that gets "
                                   "the material (0: none)")


def _label_row_picked(settings, context):
    index = settings.label_measurement_index
    if 0 <= index < len(settings.label_measurements):
        select_label(context, settings.id_data, settings.label_measurements[index].label)


class VolumeEVMLabelMeasurement(bpy.types.PropertyGroup):
    """One label's exact measurements, a row of the sidebar's list
    (``Object.volumeevm.label_measurements``, filled by Measure Labels)."""

    label: IntProperty(name="Label", description="The label's value in the label map")
    name: StringProperty(name="Name", description="The label's name from the file")
    color: FloatVectorProperty(name="Colour", size=3, subtype="COLOR", min=0.0, max=1.0)
    voxels: FloatProperty(name="Voxels", description="The label's voxels")
    volume_ml: FloatProperty(name="Volume", description="Voxels × voxel volume, in mL")
    area_mm2: FloatProperty(name="Area", description="The boundary's voxel faces, in mm²")
    components: IntProperty(name="Parts", description="Face-connected parts")


def _level_picked(settings, context):
    """A new OME-Zarr level: the object's size and spacing become that level's."""
    levels = json.loads(settings.zarr_levels or "[]")
    if not levels:
        return
    if settings.level >= len(levels):
        settings.level = len(levels) - 1  # calls this again
        return
    picked = levels[settings.level]
    settings.shape = picked["shape"]
    settings.spacing = picked["spacing"]


class VolumeEVMLabel(bpy.types.PropertyGroup):
    """One label of a label map as the volume renders show it (``Object.volumeevm.labels``,
    filled on import, :mod:`..blender.label_table`); a change redraws the viewports."""

    label: IntProperty(name="Label", description="The label's value in the label map")
    name: StringProperty(name="Name", description="The label's name from the file")
    color: FloatVectorProperty(name="Colour", size=3, subtype="COLOR", min=0.0, max=1.0,
                               update=gpu_viewport.redraw,
                               description="The label's colour in the volume renders")
    opacity: FloatProperty(name="Opacity", min=0.0, max=1.0, default=0.5,
                           update=gpu_viewport.redraw,
                           description="The label's opacity per Opacity Length of ray")
    show: BoolProperty(name="Show", default=True, update=gpu_viewport.redraw,
                       description="Show the label in the volume renders (off: transparent)")


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
            ("NATIVE", "Native Volume", "The region as a Blender Volume (OpenVDB grid)"),
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
    zarr_levels: StringProperty(
        name="OME-Zarr Levels",
        description="An OME-Zarr store's pyramid levels (JSON, from its metadata); empty for "
                    "other sources")
    level: IntProperty(
        name="Level", min=0, default=0, update=_level_picked,
        description="The OME-Zarr level Build reads, chunk by chunk (0 = full resolution)")
    built_level: IntProperty(name="Built Level", min=0,
                             description="The OME-Zarr level the VolumeEVM was built from")
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
    label_count: IntProperty(name="Labels", description="A label map's labels (0: not a label map)")
    label_measurements: CollectionProperty(
        name="Label Measurements", type=VolumeEVMLabelMeasurement,
        description="Each label's exact measurements, from Measure Labels")
    label_measurement_index: IntProperty(
        name="Picked Label", default=-1, update=_label_row_picked,
        description="The row picked in the list: selects the label's object")
    labels: CollectionProperty(
        name="Label Colours", type=VolumeEVMLabel,
        description="A label map's labels: the colour and opacity the volume renders give each")
    label_index: IntProperty(name="Active Label", default=0)
    use_label_colors: BoolProperty(
        name="Label Colours", default=True, update=gpu_viewport.redraw,
        description="Render the label map with its labels' colours and opacities (each sample "
                    "the nearest voxel's label); off: with the Render settings' colour ramp")
    units: StringProperty(
        name="Units",
        description="The data's units (e.g. HU), as the file said unless you set them; CT "
                    "presets are in HU, stretched onto the data's range only when asked")
    file_units: StringProperty(name="File Units",
                               description="The units the file said ('' = none)")
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
    crop_object: PointerProperty(
        name="Crop To", type=bpy.types.Object, poll=is_mesh_object,
        description="Build only the voxels within this object's bounds (a region of interest "
                    "of a large volume: nothing else is read or held); empty: the whole grid",
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
    tool_label: IntProperty(name="Label", min=0,
                            description="Add on a label map's label objects: the label that "
                                        "gets the material")
    # --- links between a volume and its surface
    surface: PointerProperty(name="Surface", type=bpy.types.Object,
                             description="The mesh made from this volume's VolumeEVM")
    volume: PointerProperty(name="Volume", type=bpy.types.Object,
                            description="The volume object this surface was made from")
    native: PointerProperty(name="Native Volume", type=bpy.types.Object,
                            description="The Blender Volume object made from this region")
    stack_signature: StringProperty(
        name="Stack Signature",
        description="Digest of the VolumeEVM and tool stack this surface mesh shows ('' = the "
                    "VolumeEVM itself); undo restores it with the mesh",
    )


#: Render methods: the core's records, in their order (Blender stores the setting's position).
METHOD_ITEMS = tuple((record.name, record.label, record.description)
                     for record in methods().values())
MODE_ITEMS = enum_items(MODES, {
    "over": ("Over", "Emission-absorption, front to back with early ray termination"),
    "under": ("Under", "Emission-absorption, back to front"),
    "xray": ("X-Ray", "Attenuation: exp of minus the summed density"),
    "mip": ("MIP", "Maximum intensity along each ray, classified by the transfer function"),
})
RESOLUTION_ITEMS = enum_items(LEVELS, {
    "auto": ("Auto", "Render a volume much finer than the image's pixels from a coarser level "
                     "whose voxels are still no wider than a pixel (faster, less aliasing)"),
    "full": ("Full", "Render every voxel of the VolumeEVM"),
})
#: Shear-warp's ``classification`` option.
CLASSIFICATION_ITEMS = (
    ("pre", "Pre-Classified", "Classify and shade voxels, then interpolate colours (VolPack's "
                              "order; fastest)"),
    ("post", "Post-Classified", "Interpolate densities, then classify and shade each sample "
                                "(the reference's order; sharper transfer functions)"),
)
PRESET_ITEMS = enum_items(PRESETS, {
    "ct_bone": ("CT Bone", "Bone, in Hounsfield units"),
    "ct_skin": ("CT Skin", "Skin surface over faint bone, in Hounsfield units"),
    "ct_vessels": ("CT Vessels", "Contrast-filled vessels red, bone faint, in Hounsfield units"),
    "mri": ("MRI", "Grey ramp over the data's range"),
    "microscopy": ("Microscopy", "Green fluorescence ramp over the data's range"),
})


def _is_volume(settings, obj):
    return obj.volumeevm.role == "VOLUME"


def _preset_changed(settings, context):
    load_preset(settings, settings.preset, render_volume(context, settings))


class VolumeEVMRenderSettings(bpy.types.PropertyGroup):
    """Settings of Render VolumeEVM (``Scene.volumeevm_render``): method, mode, quality and
    resolution level of the volume render; the transfer function as a colour ramp whose
    positions map onto a value range in the data's units; outputs."""

    volume: PointerProperty(name="Volume", type=bpy.types.Object, poll=_is_volume,
                            description="The volume to render (empty: the active volume)")
    viewport: BoolProperty(
        name="Viewport DVR", default=False, update=gpu_viewport.redraw,
        description="Draw the selected volumes' DVR in the 3D viewports on the GPU, with this "
                    "transfer function, mode, quality, resolution and early termination")
    viewport_fast: BoolProperty(
        name="Fast While Moving", default=True, update=gpu_viewport.redraw,
        description="While a view, a volume or its tools move, draw the Viewport DVR with one "
                    "ray per 2x2 pixels and twice the step; at full quality once it rests for "
                    "a quarter of a second")
    method: EnumProperty(name="Method", items=METHOD_ITEMS, default="raycast")
    mode: EnumProperty(name="Mode", items=MODE_ITEMS, default="over")
    quality: FloatProperty(
        name="Quality", default=1.0, min=0.05, soft_max=4.0, max=16.0,
        description="Sampling density relative to the method's default: samples per voxel "
                    "along rays (ray casting, reference), intermediate pixels per voxel "
                    "(shear-warp), sub-slabs per sheet (splatting, rounded)")
    resolution: EnumProperty(
        name="Resolution", items=RESOLUTION_ITEMS, default="auto",
        description="Resolution level of the volume render (the reference always renders every "
                    "voxel)")
    slices_per_voxel: IntProperty(
        name="Slices per Voxel", default=1, min=1, max=4,
        description="Shear-warp: samples per voxel slice along each ray (interpolated between "
                    "slices); 2 removes the jump in brightness when a turning camera passes "
                    "45 degrees to the volume's axes, at about twice the time")
    classification: EnumProperty(name="Classification", items=CLASSIFICATION_ITEMS,
                                 default="pre", description="Shear-warp: when the transfer "
                                 "function is applied")
    jitter: BoolProperty(
        name="Jitter", default=False,
        description="Ray casting: offset each ray's samples by a fixed fraction of a step, "
                    "trading wood-grain banding at coarse steps for fine noise")
    preintegrate: BoolProperty(
        name="Pre-Integrated", default=False,
        description="Ray casting: classify whole segments between samples from a table, so "
                    "narrow transfer-function peaks are not missed at coarse steps")
    shading: BoolProperty(name="Shading", default=False,
                          description="Gradient shading (Blinn-Phong, light from the camera)")
    termination: FloatProperty(
        name="Early Termination", default=0.99, min=0.5, max=1.0,
        description="Rays stop once this opaque (over mode); 1 composites every sample")
    xray_scale: FloatProperty(
        name="X-Ray Scale", default=0.01, min=0.0, soft_max=1.0, precision=4,
        description="X-ray attenuation per mm of ray per data unit above the offset")
    xray_offset: FloatProperty(
        name="X-Ray Offset", default=0.0, precision=3,
        description="Density of zero attenuation (data units, e.g. -1000 for CT air)")
    preset: EnumProperty(name="Preset", items=PRESET_ITEMS, default="ct_bone",
                         update=_preset_changed,
                         description="Load a preset into the colour ramp and value range")
    preset_stretch: BoolProperty(
        name="Stretch to Data Range", default=False, update=_preset_changed,
        description="CT presets: map their Hounsfield range -1024 .. 3071 onto the volume's "
                    "value range (CT data not stored in HU); off: the presets mean HU, as "
                    "TransferFunction.preset does in a script")
    ramp: PointerProperty(name="Transfer Function", type=bpy.types.Texture,
                          description="Blend texture whose colour ramp is the transfer function")
    value_lo: FloatProperty(name="Low", default=-1024.0, precision=3,
                            description="Data value at the ramp's left end (data units)")
    value_hi: FloatProperty(name="High", default=3071.0, precision=3,
                            description="Data value at the ramp's right end (data units)")
    unit_length_mm: FloatProperty(
        name="Opacity Length", default=1.0, min=1e-4, soft_max=100.0, unit="NONE",
        description="The ramp's alpha is the opacity over this many mm of ray")
    image_name: StringProperty(name="Image", default=DEFAULT_IMAGE,
                               description="Image datablock of the composite (the volume alone "
                                           "goes to '<Image> DVR')")
    hide_surface: BoolProperty(
        name="Hide Surface", default=True,
        description="Leave the volume's own surface mesh out of the scene render (the volume "
                    "render shows the volume)")
    use_exr: BoolProperty(name="EXR", default=False, description="Write R, G, B, A, Z to EXR")
    exr_path: StringProperty(name="EXR File", subtype="FILE_PATH", default="//volumeevm.exr",
                             options={"PATH_SUPPORTS_BLEND_RELATIVE"})
    use_png: BoolProperty(name="PNG", default=False,
                          description="Write a PNG (through the scene's view transform)")
    png_path: StringProperty(name="PNG File", subtype="FILE_PATH", default="//volumeevm.png",
                             options={"PATH_SUPPORTS_BLEND_RELATIVE"})
    overwrite: BoolProperty(name="Overwrite", default=False,
                            description="Replace existing files (off: refuse)")
    allow_stale_dvr: BoolProperty(
        name="Allow Stale DVR", default=False,
        description="F12 lays the DVR image over the render even when it was rendered for "
                    "another frame, camera or resolution (off: F12 leaves it out and says so)")


CLASSES = [VolumeEVMSceneSettings, VolumeEVMToolEntry, VolumeEVMLabelMeasurement,
           VolumeEVMLabel, VolumeEVMObjectSettings,
           VolumeEVMRenderSettings]
