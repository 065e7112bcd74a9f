"""The sidebar's Render section and its settings (``Scene.volumeevm_render``).

Method, mode, quality and resolution level of the volume render; the transfer function as a colour ramp whose
positions map onto a value range in the data's units (histogram beside it); outputs.
"""

import bpy
import numpy as np
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..operators import _jobs, dvr, render

METHOD_ITEMS = (
    ("raycast", "Ray Casting", "Trilinear ray casting with the EVM as space-leaping structure"),
    ("shear_warp", "Shear-Warp", "Sheared slices, one intermediate image, one 2D warp (fast)"),
    ("splat", "Splatting", "Voxel footprints, sheet by sheet along the principal axis"),
    ("raycast_navigate", "Ray Casting (Navigation)",
     "Ray casting that finds every density through the EVM (the report's slow baseline)"),
    ("reference", "Reference", "Dense float64 ray caster with a tiny step (accuracy oracle, slow)"),
)
MODE_ITEMS = (
    ("over", "Over", "Emission-absorption, front to back with early ray termination"),
    ("under", "Under", "Emission-absorption, back to front"),
    ("xray", "X-Ray", "Attenuation: exp of minus the summed density"),
    ("mip", "MIP", "Maximum intensity along each ray, classified by the transfer function"),
)
RESOLUTION_ITEMS = (
    ("auto", "Auto", "Render a volume much finer than the image's pixels from a coarser level "
                     "whose voxels are still no wider than a pixel (faster, less aliasing)"),
    ("full", "Full", "Render every voxel of the VolumeEVM"),
)
CLASSIFICATION_ITEMS = (
    ("pre", "Pre-Classified", "Classify and shade voxels, then interpolate colours (VolPack's "
                              "order; fastest)"),
    ("post", "Post-Classified", "Interpolate densities, then classify and shade each sample "
                                "(the reference's order; sharper transfer functions)"),
)
PRESET_ITEMS = (
    ("ct_bone", "CT Bone", "Bone, in Hounsfield units"),
    ("ct_skin", "CT Skin", "Skin surface over faint bone, in Hounsfield units"),
    ("ct_vessels", "CT Vessels", "Contrast-filled vessels red, bone faint, in Hounsfield units"),
    ("mri", "MRI", "Grey ramp over the data's range"),
    ("microscopy", "Microscopy", "Green fluorescence ramp over the data's range"),
)


def _is_volume(settings, obj):
    return obj.volumeevm.role == "VOLUME"


def _preset_changed(settings, context):
    render.load_preset(settings, settings.preset, render.render_volume(context, settings))


class VolumeEVMRenderSettings(bpy.types.PropertyGroup):
    """Settings of Render VolumeEVM (``Scene.volumeevm_render``)."""

    volume: PointerProperty(name="Volume", type=bpy.types.Object, poll=_is_volume,
                            description="The volume to render (empty: the active volume)")
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
    ramp: PointerProperty(name="Transfer Function", type=bpy.types.Texture,
                          description="Blend texture whose colour ramp is the transfer function")
    value_lo: FloatProperty(name="Low", default=-1024.0, precision=3,
                            description="Data value at the ramp's left end (data units)")
    value_hi: FloatProperty(name="High", default=3071.0, precision=3,
                            description="Data value at the ramp's right end (data units)")
    unit_length_mm: FloatProperty(
        name="Opacity Length", default=1.0, min=1e-4, soft_max=100.0, unit="NONE",
        description="The ramp's alpha is the opacity over this many mm of ray")
    image_name: StringProperty(name="Image", default=dvr.DEFAULT_IMAGE,
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


#: Histogram rows drawn beside the ramp.
HISTOGRAM_ROWS = 8


def draw_histogram(layout, s, lo, hi):
    """The volume's histogram in a few rows, the rows inside the ramp's range ticked."""
    counts = np.asarray(s.histogram, np.float64)
    if counts.sum() == 0:
        return
    counts = counts.reshape(HISTOGRAM_ROWS, -1).sum(axis=1)
    heights = np.log1p(counts)
    heights = heights / heights.max()
    edges = np.linspace(s.value_min, s.value_max, HISTOGRAM_ROWS + 1)
    col = layout.column(align=True)
    for i in range(HISTOGRAM_ROWS):
        row = col.row(align=True)
        row.scale_y = 0.6
        inside = edges[i + 1] > lo and edges[i] < hi
        row.label(text="", icon="CHECKMARK" if inside else "BLANK1")
        row.progress(factor=float(heights[i]), type="BAR", text=f"{edges[i]:.4g}")


class VOLUMEEVM_PT_render(bpy.types.Panel):
    """Direct volume rendering from the VolumeEVM, composited into the scene render."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VolumeEVM"
    bl_label = "Render"
    bl_parent_id = "VOLUMEEVM_PT_main"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.volumeevm_render
        layout.use_property_split = True
        layout.use_property_decorate = False
        layout.prop(settings, "volume")
        vol = render.render_volume(context, settings)
        if settings.volume is None and vol is not None:
            layout.label(text=f"Rendering {vol.name}", icon="INFO")
        col = layout.column(align=True)
        col.prop(settings, "method")
        col.prop(settings, "mode")
        col.prop(settings, "quality")
        col.prop(settings, "resolution")
        col.prop(settings, "termination")
        if settings.method == "shear_warp":
            col.prop(settings, "slices_per_voxel")
            col.prop(settings, "classification")
        elif settings.method in ("raycast", "raycast_navigate"):
            col.prop(settings, "jitter")
            col.prop(settings, "preintegrate")
        col.prop(settings, "shading")
        if settings.mode == "xray":
            col.prop(settings, "xray_scale")
            col.prop(settings, "xray_offset")

        box = layout.box()
        box.label(text="Transfer Function", icon="COLOR")
        row = box.row(align=True)
        row.prop(settings, "preset", text="")
        row.operator("volumeevm.load_tf_preset", text="", icon="FILE_REFRESH")
        if settings.ramp is not None and settings.ramp.color_ramp is not None:
            box.template_color_ramp(settings.ramp, "color_ramp", expand=True)
        else:
            box.label(text="Load a preset to edit the ramp")
        units = vol.volumeevm.units if vol is not None else ""
        row = box.row(align=True)
        row.prop(settings, "value_lo", text="")
        row.prop(settings, "value_hi", text="")
        if units:
            row.label(text=units)
        box.prop(settings, "unit_length_mm", text="Alpha per mm")
        if vol is not None:
            draw_histogram(box, vol.volumeevm, settings.value_lo, settings.value_hi)

        col = layout.column(align=True)
        col.prop(settings, "image_name")
        col.prop(settings, "hide_surface")
        row = col.row(align=True)
        row.prop(settings, "use_exr", text="EXR")
        sub = row.row(align=True)
        sub.active = settings.use_exr
        sub.prop(settings, "exr_path", text="")
        row = col.row(align=True)
        row.prop(settings, "use_png", text="PNG")
        sub = row.row(align=True)
        sub.active = settings.use_png
        sub.prop(settings, "png_path", text="")
        col.prop(settings, "overwrite")

        if _jobs.CURRENT is not None:
            layout.label(text="Press Esc to cancel", icon="INFO")
        layout.operator("volumeevm.render_dvr", icon="RENDER_STILL")
        layout.operator("volumeevm.render_dvr_animation", icon="RENDER_ANIMATION")
        layout.operator("volumeevm.setup_compositor", icon="NODE_COMPOSITING")
        if context.scene.camera is None:
            layout.label(text="The scene has no camera", icon="ERROR")


CLASSES = [VolumeEVMRenderSettings, VOLUMEEVM_PT_render]


def register():
    """Register the settings and the panel, and attach ``Scene.volumeevm_render``."""
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.volumeevm_render = PointerProperty(type=VolumeEVMRenderSettings)


def unregister():
    del bpy.types.Scene.volumeevm_render
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
