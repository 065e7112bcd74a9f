"""Render VolumeEVM (DVR composited into the scene) and the compositor set-up for F12.

Operators:

- ``volumeevm.render_dvr``: the sidebar's Render settings (``Scene.volumeevm_render``) ->
  :func:`.dvr.render_dvr_job` (scene pass, volume render, alpha over, images, files).
- ``volumeevm.setup_compositor``: :func:`setup_compositor`, the DVR image laid over the Render
  Layers image (Alpha Over, premultiplied) in the scene's compositor, so F12 renders and
  animations include it. Works on the 4.x compositor (``scene.use_nodes``, ``scene.node_tree``,
  Composite node) and the 5.x one (``scene.compositing_node_group``: a CompositorNodeTree with
  an Image output socket and a Group Output node).
- ``volumeevm.load_tf_preset``: a preset into the transfer function's colour ramp.

Caveat of the compositor path: the compositor lays the DVR image as it was last rendered. Render
it (Render VolumeEVM) with the same camera, frame and resolution before F12; the volume's rays
stop at the depth of the scene as it was then (the scene cannot be rendered again from inside
its own render, so F12 alone cannot make a depth-correct DVR of a changed scene). A
``render_pre`` handler (:func:`check_view`) prints a warning when F12 starts with a DVR image
rendered for another frame, camera or resolution. For animations use Render VolumeEVM
Animation (``volumeevm.render_dvr_animation``, :func:`.dvr.render_dvr_animation`), which
renders scene pass, DVR and composite frame by frame.

The transfer function is a colour ramp (a Blend texture's ``color_ramp``): element position
``p`` stands for the value ``lo + p (hi - lo)`` in the data's own units, its colour for the
straight colour and its alpha for the opacity per ``unit_length_mm`` mm of ray.
"""


import bpy
import numpy as np
from bpy.props import StringProperty

from ..volumeevm_addon import PRESETS, TransferFunction, VolumeEVMError
from . import _jobs, api, dvr
from .build import active_volume

__all__ = ["setup_compositor", "transfer_function", "load_preset", "set_transfer_function",
           "render_volume",
           "ensure_ramp", "CT_RANGE"]

#: Node names of the compositor set-up (found again, never duplicated).
NODE_IMAGE = "VolumeEVM DVR"
NODE_OVER = "VolumeEVM Over"
#: The Hounsfield range the CT presets are written for; mapped onto non-HU data's range.
CT_RANGE = (-1024.0, 3071.0)
RAMP_NAME = "VolumeEVM Transfer Function"


# ---------------------------------------------------------------------------- transfer function
def ensure_ramp(settings):
    """The settings' colour-ramp texture (made, with the settings' preset, if missing)."""
    if settings.ramp is None:
        texture = bpy.data.textures.new(RAMP_NAME, "BLEND")
        texture.use_color_ramp = True
        settings.ramp = texture
        load_preset(settings, settings.preset, render_volume(bpy.context, settings))
    return settings.ramp


def transfer_function(settings):
    """The :class:`TransferFunction` of the settings' colour ramp over ``[value_lo, value_hi]``.

    Positions that coincide (a step) are moved apart by 1e-6 of the range; colours are clamped
    to ``[0, 1]``. The ramp's interpolation is taken as linear whatever it shows.
    """
    texture = settings.ramp
    if texture is None or texture.color_ramp is None:
        raise VolumeEVMError("no transfer function yet: load a preset in the Render panel")
    lo, hi = float(settings.value_lo), float(settings.value_hi)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise VolumeEVMError(f"transfer function range: need low < high, got {lo} .. {hi}")
    elements = texture.color_ramp.elements
    positions = np.empty(len(elements), np.float64)
    elements.foreach_get("position", positions)
    colours = np.empty(len(elements) * 4, np.float32)
    elements.foreach_get("color", colours)
    colours = np.clip(colours.reshape(-1, 4).astype(np.float64), 0.0, 1.0)
    order = np.argsort(positions, kind="stable")
    positions, colours = positions[order], colours[order]
    nudge = np.arange(len(positions)) * 1e-6  # strictly increasing even for equal positions
    values = lo + (positions + nudge) * (hi - lo)
    points = np.column_stack([values, colours])
    return TransferFunction(points, unit_length_mm=settings.unit_length_mm, name=settings.preset)


def load_preset(settings, name, vol_obj=None):
    """Write preset ``name`` into the settings' ramp and value range.

    CT presets are in Hounsfield units; for a volume whose units are not HU they are stretched
    from :data:`CT_RANGE` onto the volume's value range. ``mri`` and ``microscopy`` take the
    volume's value range (0 .. 1 without a volume).
    """
    if name not in PRESETS:
        raise VolumeEVMError(f"preset must be one of {PRESETS}, got {name!r}")
    data_range = (0.0, 1.0)
    units = ""
    if vol_obj is not None:
        s = vol_obj.volumeevm
        units = s.units
        if s.value_max > s.value_min:
            data_range = (float(s.value_min), float(s.value_max))
    tf = TransferFunction.preset(name, data_range=data_range)
    points = np.array(tf.points, np.float64)
    if name.startswith("ct_") and vol_obj is not None and units != "HU":
        (a, b), (c, d) = CT_RANGE, data_range
        points[:, 0] = c + (points[:, 0] - a) * (d - c) / (b - a)
    set_transfer_function(settings, TransferFunction(points, name=name))
    if settings.preset != name:
        settings.preset = name


def set_transfer_function(settings, tf):
    """Write ``tf`` into the settings' colour ramp, value range and opacity length.

    A ramp holds at most 32 elements; ``tf`` must not have more control points.
    """
    points = np.asarray(tf.points, np.float64)
    if len(points) > 32:
        raise VolumeEVMError(f"tf: a colour ramp holds 32 points, the function has {len(points)}")
    lo, hi = float(points[0, 0]), float(points[-1, 0])
    if hi <= lo:
        hi = lo + 1.0
    texture = settings.ramp
    if texture is None:
        texture = bpy.data.textures.new(RAMP_NAME, "BLEND")
        texture.use_color_ramp = True
        settings.ramp = texture
    ramp = texture.color_ramp
    ramp.interpolation = "LINEAR"
    ramp.color_mode = "RGB"
    elements = ramp.elements
    while len(elements) > 1:
        elements.remove(elements[-1])
    elements[0].position = 0.0
    for _ in range(len(points) - 1):
        elements.new(1.0)
    positions = (points[:, 0] - lo) / (hi - lo)
    for element, position, row in zip(elements, positions, points):
        element.position = float(position)
        element.color = tuple(float(v) for v in row[1:5])
    settings.value_lo, settings.value_hi = lo, hi
    settings.unit_length_mm = tf.unit_length_mm


# ---------------------------------------------------------------------------- compositor
def _over_sockets(node):
    """(background, foreground) inputs of an Alpha Over node (5.x names them; 4.x does not)."""
    if "Background" in node.inputs:
        return node.inputs["Background"], node.inputs["Foreground"]
    return node.inputs[1], node.inputs[2]


def _node(tree, name, kind):
    node = tree.nodes.get(name)
    if node is None or node.bl_idname != kind:
        node = tree.nodes.new(kind)
        node.name = node.label = name
    return node


def _first(tree, kind):
    return next((n for n in tree.nodes if n.bl_idname == kind), None)


def setup_compositor(scene, image):
    """Lay ``image`` (premultiplied) over the render in ``scene``'s compositor.

    Whatever fed the compositor's output stays as the background (the Render Layers image in a
    new set-up); running it again only points the Image node at ``image``.

    Parameters
    ----------
    scene : bpy.types.Scene
    image : bpy.types.Image
        The DVR alone (``dvr.DEFAULT_IMAGE + " DVR"``), premultiplied.

    Returns
    -------
    bpy.types.NodeTree
        The compositing tree (5.x: ``scene.compositing_node_group``; 4.x: ``scene.node_tree``).
    """
    if hasattr(scene, "compositing_node_group"):  # Blender 5.x
        tree = scene.compositing_node_group
        if tree is None:
            tree = bpy.data.node_groups.new("VolumeEVM Compositing", "CompositorNodeTree")
            scene.compositing_node_group = tree
        if not any(item.item_type == "SOCKET" and item.in_out == "OUTPUT"
                   for item in tree.interface.items_tree):
            tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        output = _first(tree, "NodeGroupOutput") or tree.nodes.new("NodeGroupOutput")
        target = output.inputs[0]
    else:  # Blender 4.x
        scene.use_nodes = True
        tree = scene.node_tree
        output = _first(tree, "CompositorNodeComposite") or tree.nodes.new(
            "CompositorNodeComposite")
        target = output.inputs["Image"]
    scene.render.use_compositing = True
    layers = _first(tree, "CompositorNodeRLayers")
    if layers is None:
        layers = tree.nodes.new("CompositorNodeRLayers")
        layers.location = (output.location.x - 600, output.location.y)
    image_node = _node(tree, NODE_IMAGE, "CompositorNodeImage")
    image_node.image = image
    over = _node(tree, NODE_OVER, "CompositorNodeAlphaOver")
    over.location = (output.location.x - 220, output.location.y)
    image_node.location = (over.location.x - 260, over.location.y - 220)
    background, foreground = _over_sockets(over)
    feeding = target.links[0].from_socket if target.is_linked else None
    if feeding is not None and feeding.node != over:
        tree.links.new(feeding, background)
    elif not background.is_linked:
        tree.links.new(layers.outputs["Image"], background)
    tree.links.new(image_node.outputs["Image"], foreground)
    tree.links.new(over.outputs[0], target)
    return tree


# ---------------------------------------------------------------------------- operators
def render_volume(context, settings):
    """The volume to render: the settings' volume, else the active one, else the only one."""
    if settings.volume is not None:
        return settings.volume
    obj = active_volume(context)
    if obj is not None:
        return obj
    volumes = [o for o in context.scene.objects if o.volumeevm.role == "VOLUME"]
    return volumes[0] if len(volumes) == 1 else None


def _render_problem(context):
    scene = context.scene
    settings = scene.volumeevm_render
    vol = render_volume(context, settings)
    if vol is None:
        return "Choose the volume to render (or select one)"
    if not vol.volumeevm.vevm_path:
        return f"{vol.name}: build the VolumeEVM first"
    if scene.camera is None:
        return "The scene has no camera"
    if _jobs.CURRENT is not None:
        return f"Busy: {_jobs.CURRENT.label}"
    return ""


class VOLUMEEVM_OT_render_dvr(_jobs.JobOperator, bpy.types.Operator):
    """Render the scene with its depth pass, render the volume from the scene camera with rays
    stopped by that depth, lay it over the render and keep the result in an image (and files)"""

    bl_idname = "volumeevm.render_dvr"
    bl_label = "Render VolumeEVM"
    bl_options = {"REGISTER"}

    volume: StringProperty(
        name="Volume", options={"SKIP_SAVE"},
        description="Name of the volume object (default: the Render settings' volume, else the "
                    "active one)")

    @classmethod
    def poll(cls, context):
        if not hasattr(context.scene, "volumeevm_render"):
            return False
        problem = _render_problem(context)
        if problem and not problem.startswith("The scene has no camera"):
            cls.poll_message_set(problem)
            return False
        return True

    def job(self, context):
        scene = context.scene
        vol, tf, kwargs = _job_arguments(context, scene.volumeevm_render, self.volume)
        return dvr.render_dvr_job(scene, vol, tf, **kwargs)

    def finished(self, context, result):
        h, w = result.rgba.shape[:2]
        files = [p for p in (result.exr_path, result.png_path) if p]
        if not result.visible:
            self.report({"WARNING"}, "The camera sees nothing of the volume (outside the view, "
                                     "hidden by scene geometry or transparent): the DVR is empty")
        else:
            self.report({"INFO"}, f"{result.image.name}: {w}x{h}"
                                  + (f", wrote {', '.join(files)}" if files else ""))
        # Show the result in an open Image Editor, if any.
        screen = context.screen
        for area in (screen.areas if screen is not None else ()):
            if area.type == "IMAGE_EDITOR":
                _jobs.assign(area.spaces.active, image=result.image)


def _job_arguments(context, settings, volume_name=""):
    """Volume, transfer function and keyword arguments of a render from the settings."""
    if volume_name:
        vol = bpy.data.objects.get(volume_name)
        if vol is None:
            raise VolumeEVMError(f"no object named {volume_name!r}")
    else:
        vol = render_volume(context, settings)
        if vol is None:
            raise VolumeEVMError("choose the volume to render (or select one)")
    vol = api.volume_object(vol)
    ensure_ramp(settings)
    tf = transfer_function(settings)
    options = dvr.method_options(settings.method, settings.quality, tuple(vol.volumeevm.spacing),
                                 shading=settings.shading, termination=settings.termination,
                                 level=settings.resolution,
                                 slices_per_voxel=settings.slices_per_voxel,
                                 classification=settings.classification,
                                 jitter=settings.jitter, preintegrate=settings.preintegrate)
    if settings.mode == "xray":
        options.update(xray_scale=settings.xray_scale, xray_offset=settings.xray_offset)
    return vol, tf, dict(
        method=settings.method, mode=settings.mode, options=options,
        image_name=settings.image_name or dvr.DEFAULT_IMAGE,
        exr_path=settings.exr_path if settings.use_exr else "",
        png_path=settings.png_path if settings.use_png else "",
        overwrite=settings.overwrite, hide_surface=settings.hide_surface)


class VOLUMEEVM_OT_render_dvr_animation(bpy.types.Operator):
    """Render VolumeEVM for every frame of the scene's range (scene pass, volume render and
    composite per frame), writing the EXR/PNG files with the frame number ('#' in the names)"""

    bl_idname = "volumeevm.render_dvr_animation"
    bl_label = "Render VolumeEVM Animation"
    bl_options = {"REGISTER"}

    volume: StringProperty(name="Volume", options={"SKIP_SAVE"},
                           description="Name of the volume object (default: as Render VolumeEVM)")

    @classmethod
    def poll(cls, context):
        return VOLUMEEVM_OT_render_dvr.poll(context)

    def execute(self, context):
        scene = context.scene
        wm = context.window_manager
        try:
            vol, tf, kwargs = _job_arguments(context, scene.volumeevm_render, self.volume)
            if not (kwargs["exr_path"] or kwargs["png_path"]):
                raise VolumeEVMError("choose an EXR or PNG file name for the frames")
            wm.progress_begin(scene.frame_start, scene.frame_end)
            try:
                results = dvr.render_dvr_animation(vol, tf, scene=scene, **kwargs)
            finally:
                wm.progress_end()
        except _jobs.REPORTED_ERRORS as error:
            return _jobs.report_failure(self, error)
        empty = [frame for frame, result in results if not result.visible]
        if empty:
            self.report({"WARNING"}, f"nothing of the volume seen in frames {empty}")
        self.report({"INFO"}, f"rendered {len(results)} frames")
        return {"FINISHED"}


def _compositor_image(scene):
    """The image the scene's VolumeEVM compositor node shows, or None."""
    tree = getattr(scene, "compositing_node_group", None)
    if tree is None and not hasattr(scene, "compositing_node_group"):
        tree = scene.node_tree if scene.use_nodes else None
    node = tree.nodes.get(NODE_IMAGE) if tree is not None else None
    if node is None or node.mute or node.image is None:
        return None
    return node.image


@bpy.app.handlers.persistent
def check_view(scene, *_args):
    """render_pre: warn when the compositor's DVR image was rendered for another view."""
    image = _compositor_image(scene)
    if image is None or not scene.render.use_compositing:
        return
    stored = image.get(dvr.VIEW_KEY)
    if stored != dvr.view_signature(scene):
        print(f"[volumeevm] warning: {image.name!r} was rendered for another frame, camera or "
              f"resolution than this render's; run Render VolumeEVM again (or Render VolumeEVM "
              f"Animation)", flush=True)


HANDLERS = (("render_pre", check_view),)


class VOLUMEEVM_OT_setup_compositor(bpy.types.Operator):
    """Lay the rendered volume image over the Render Layers in the compositor, so F12 renders
    include it (render the volume first, with the same camera and frame)"""

    bl_idname = "volumeevm.setup_compositor"
    bl_label = "Set Up Compositor"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        settings = scene.volumeevm_render
        name = f"{settings.image_name or dvr.DEFAULT_IMAGE} DVR"
        image = bpy.data.images.get(name)
        if image is None:
            r = scene.render
            w = r.resolution_x * r.resolution_percentage // 100
            h = r.resolution_y * r.resolution_percentage // 100
            image = dvr.put_image(name, np.zeros((h, w, 4), np.float32))
            self.report({"WARNING"}, f"{name} is empty: Render VolumeEVM first, then F12")
        setup_compositor(scene, image)
        return {"FINISHED"}


class VOLUMEEVM_OT_load_tf_preset(bpy.types.Operator):
    """Load the chosen preset into the transfer function's colour ramp and value range"""

    bl_idname = "volumeevm.load_tf_preset"
    bl_label = "Load Preset"
    bl_options = {"REGISTER", "UNDO"}

    preset: StringProperty(name="Preset", options={"SKIP_SAVE"},
                           description="Preset name (default: the Render settings' preset)")

    def execute(self, context):
        settings = context.scene.volumeevm_render
        try:
            load_preset(settings, self.preset or settings.preset,
                        render_volume(context, settings))
        except VolumeEVMError as error:
            return _jobs.report_failure(self, error)
        return {"FINISHED"}


CLASSES = [VOLUMEEVM_OT_render_dvr, VOLUMEEVM_OT_render_dvr_animation,
           VOLUMEEVM_OT_setup_compositor, VOLUMEEVM_OT_load_tf_preset]
