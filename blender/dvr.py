"""The DVR render job: the Blender scene, its depth pass, the core's volume render, the composite.

How one render goes (:func:`render_dvr_job`; the operator ``volumeevm.render_dvr`` and the
script function :func:`render_dvr` run the same job):

1. **Scene pass** (main thread, :func:`.scene.render_scene`): the scene rendered by its own
   engine with the Depth pass; the volume's own surface mesh is hidden for it (the DVR shows
   the volume) unless asked not to.
2. **Camera**: :func:`.camera.camera_from_blender` (the scene camera, or the one given).
3. **Volume render** (a worker thread in the UI): the core's ``render(vevm, camera, tf,
   method=, mode=, depth_in=scene_depth, matrix_world=volume.matrix_world, **options)``; rays
   stop at the scene's geometry. The VolumeEVM is the tool stack's result when the volume has
   tools. The Render setting Resolution (``level`` of the core's ``method_options``, Auto by
   default) renders a volume much finer than the image's pixels from a coarser level of it.
   The method ``"gpu"`` (:mod:`.gpu_draw`, the same outputs) draws on the main thread right
   after the scene pass; where no GPU context can be made the CPU ray caster renders instead,
   with the same options, and the result's ``note`` says so.
4. **Composite**: the core's ``composite_over`` (``out = dvr + (1 - dvr.a) · scene``) and
   ``output_depth`` (the DVR's depth where it is visible, else the scene's; axial, Blender
   units, 1e10 = nothing).
5. **Images and files** (main thread, :mod:`.images`): two float Image datablocks (bottom row
   first, alpha premultiplied, scene-linear): ``<name>`` holds the composite and ``<name> DVR``
   the volume alone (the compositor set-up lays that one over the Render Layers,
   :mod:`.compositor`). Optional EXR (R, G, B, A, Z) and PNG (the scene's view transform
   applied, as F12 saves it), both written atomically and never over an existing file unless
   ``overwrite``. All or nothing: if any part of this step (or the operator's report after it)
   fails, the images get their names, sizes and pixels back, new files are removed and
   replaced ones come back.

Caveats: the Depth pass is one sample per pixel (not anti-aliased), so the edge of geometry in
front of the volume can show a one-pixel fringe; motion blur and panoramic cameras are not
supported; a render border is ignored (the whole frame is rendered).
"""

import functools
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import TransferFunction, VolumeEVMError, render
from ..volumeevm_addon.rendering import composite_over, method_options, methods, output_depth
from ..volumeevm_addon.system import atomic_target
from . import exr, gpu_context, gpu_draw, images, jobs
from .camera import camera_from_blender
from .objects import get_vevm, own_surface, render_volume, volume_object
from .scene import SceneRender, render_layer, render_scene
from .tool_stack import evaluate
from .transfer import ensure_ramp, volume_transfer_function

#: Name of the composite Image datablock (the DVR alone is ``DEFAULT_IMAGE + " DVR"``).
DEFAULT_IMAGE = "VolumeEVM Render"
#: Custom property of the DVR image: the view it was rendered for (see :func:`view_signature`).
VIEW_KEY = "volumeevm_view"
#: The methods of Render VolumeEVM: the core's records (``volumeevm_addon.rendering.methods()``),
#: the CPU's and the GPU's (drawn by :mod:`.gpu_draw`).
METHODS = tuple(methods())


@dataclass
class DVRResult:
    """What one DVR render made (arrays: float32, row 0 at the top)."""

    rgba: np.ndarray  # (H, W, 4) composite, premultiplied
    depth: np.ndarray  # (H, W) output Z: DVR depth where visible, else the scene's
    dvr_rgba: np.ndarray  # (H, W, 4) the volume alone, premultiplied
    dvr_depth: np.ndarray  # (H, W) axial depth of the first visible sample, 1e10 where none
    scene: SceneRender
    image: object = None  # bpy.types.Image of the composite
    dvr_image: object = None  # bpy.types.Image of the volume alone
    exr_path: str = ""
    png_path: str = ""
    visible: bool = True  # False: nothing of the volume was seen (transparent DVR)
    note: str = ""  # what the user should know: the GPU fell back to the CPU or drew a level


def volume_for_render(vol_obj):
    """The VolumeEVM to render: the tool stack's result if the volume has tools, else its own."""
    vol_obj = volume_object(vol_obj)
    if len(vol_obj.volumeevm.tools):
        return evaluate(vol_obj)
    return get_vevm(vol_obj)


def view_signature(scene, camera_object=None):
    """A string naming what a DVR image depends on besides the volume: frame, camera (placement
    and lens), resolution. The compositor's render_pre check compares it (:mod:`.compositor`)."""
    obj = scene.camera if camera_object is None else camera_object
    r = scene.render
    parts = [f"frame {scene.frame_current}",
             f"size {r.resolution_x}x{r.resolution_y}@{r.resolution_percentage}%",
             f"aspect {r.pixel_aspect_x:.6g}:{r.pixel_aspect_y:.6g}"]
    if obj is None:
        parts.append("no camera")
    else:
        m = np.round(np.array(obj.matrix_world, np.float64), 6) + 0.0  # no -0.0
        cam = obj.data
        lens = getattr(cam, "lens", 0.0)
        parts.append(f"camera {obj.name} {getattr(cam, 'type', '')} lens {lens:.6g} ortho "
                     f"{getattr(cam, 'ortho_scale', 0.0):.6g} shift "
                     f"{getattr(cam, 'shift_x', 0.0):.6g},{getattr(cam, 'shift_y', 0.0):.6g} "
                     f"fit {getattr(cam, 'sensor_fit', '')} matrix {m.ravel().tolist()}")
    return "; ".join(parts)


def frame_path(path, frame):
    """``path`` with its last run of ``#`` replaced by the zero-padded frame number (or
    ``_####`` added before the suffix when it has none), as Blender names animation frames."""
    path = str(path)
    end = path.rfind("#")
    if end < 0:
        stem = Path(path)
        return str(stem.with_name(f"{stem.stem}_{frame:04d}{stem.suffix}"))
    start = end
    while start > 0 and path[start - 1] == "#":
        start -= 1
    return f"{path[:start]}{frame:0{end - start + 1}d}{path[end + 1:]}"


def absolute_path(path, name):
    """``path`` ("" = none) made absolute; ``//`` is the .blend's folder.

    Raises
    ------
    VolumeEVMError
        ``path`` starts with ``//`` while the .blend is not saved (it has no folder yet: Blender
        would resolve it against the current directory).
    """
    if not path:
        return ""
    if path.startswith("//") and not bpy.data.filepath:
        raise VolumeEVMError(f"{name}: {path!r} is relative to the .blend file, which is not "
                             f"saved yet; save the .blend first or give a full path")
    return str(Path(bpy.path.abspath(path)))


def render_dvr_job(scene, volume_obj, tf, *, method="raycast", mode="over", options=None,
                   camera_object=None, image_name=DEFAULT_IMAGE, exr_path="", png_path="",
                   overwrite=False, hide_surface=True):
    """The DVR job (see :func:`render_dvr`). The scene pass runs here, on the calling thread."""
    if not isinstance(tf, TransferFunction):
        raise VolumeEVMError(f"tf: expected a TransferFunction, got {type(tf).__name__}")
    if method not in METHODS:
        raise VolumeEVMError(f"method: one of {METHODS}, got {method!r}")
    vol_obj = volume_object(volume_obj)
    render_layer(scene).update()  # placements changed since the last update (scripts)
    camera = camera_from_blender(scene, camera_object)
    exr_path, png_path = absolute_path(exr_path, "exr_path"), absolute_path(png_path, "png_path")
    for path in (exr_path, png_path):
        if path:
            atomic_target(path, overwrite=overwrite)  # fail before the slow part
    vevm = volume_for_render(vol_obj)
    matrix_world = np.array(vol_obj.matrix_world, np.float64)
    hide = []
    if hide_surface:
        surface = own_surface(vol_obj)
        if surface is not None:
            hide.append(surface)
    if bpy.app.background:
        print(jobs.progress_line(0.0, f"rendering scene {scene.name!r} ({scene.render.engine})"),
              flush=True)
    scene_pass = render_scene(scene, camera_object=camera_object, hide=hide)
    if scene_pass.depth.shape != camera.shape:
        raise VolumeEVMError(f"scene render is {scene_pass.depth.shape[::-1]} pixels, the camera "
                             f"{camera.shape[::-1]}")
    options = {"level": "auto", **(options or {})}  # the Render setting Resolution's default
    signature = view_signature(scene, camera_object)
    drawn, note = None, ""
    record = methods()[method]
    if record.gpu:  # drawn here: GPU work belongs to the main thread
        try:
            *drawn, level = gpu_draw.render_gpu(vevm, camera, tf, mode=mode,
                                                depth_in=scene_pass.depth,
                                                matrix_world=matrix_world, **options)
            if level > 1:  # say which level the GPU drew
                note = f"rendered from {gpu_draw.level_text(level)}"
        except gpu_context.GPUUnavailable as error:
            method = record.fallback
            note = (f"{error}: rendered with {methods()[method].label.lower()} on the CPU "
                    f"instead")

    def steps():
        yield 0.2, f"volume render ({method}, {mode})"
        if drawn is None:
            dvr_rgba, dvr_depth = render(vevm, camera, tf, method=method, mode=mode,
                                         depth_in=scene_pass.depth, matrix_world=matrix_world,
                                         **options)
        else:
            dvr_rgba, dvr_depth = drawn
        yield 0.9, "compositing"
        dvr_rgba = np.nan_to_num(np.asarray(dvr_rgba, np.float32))
        rgba = composite_over(dvr_rgba, scene_pass.rgba)
        depth = output_depth(dvr_depth, scene_pass.depth)
        return DVRResult(rgba, depth, dvr_rgba, np.asarray(dvr_depth, np.float32), scene_pass,
                         visible=bool((dvr_rgba[..., 3] > 0).any()), note=note)

    def commit(result):  # all undone if it (or the operator's report) fails
        result.image = images.put_image(image_name, result.rgba)
        result.dvr_image = images.put_image(f"{image_name} DVR", result.dvr_rgba)
        jobs.assign_item(result.dvr_image, VIEW_KEY, signature)
        if exr_path:
            result.exr_path = str(images.write_file(exr_path, functools.partial(
                exr.write_exr, exr_path, result.rgba, result.depth, overwrite=overwrite),
                overwrite=overwrite))
        if png_path:
            result.png_path = str(images.write_file(png_path, functools.partial(
                images.write_png, result.image, png_path, scene, overwrite=overwrite),
                overwrite=overwrite))
        return result

    return jobs.Job(f"Render {vol_obj.name}", steps(), commit)


def settings_options(settings, vol, method):
    """The options of ``method`` that the Render settings (``Scene.volumeevm_render``) ask
    for a volume object ``vol``: the core's ``method_options`` (each setting only to the
    methods that take it), X-ray's with ``mode="xray"``."""
    options = method_options(method, settings.quality, tuple(vol.volumeevm.spacing),
                             shading=settings.shading, termination=settings.termination,
                             level=settings.resolution,
                             slices_per_voxel=settings.slices_per_voxel,
                             classification=settings.classification,
                             jitter=settings.jitter, preintegrate=settings.preintegrate)
    if settings.mode == "xray":
        options.update(xray_scale=settings.xray_scale, xray_offset=settings.xray_offset)
    return options


def job_arguments(context, settings, volume_name=""):
    """The volume, transfer function and keyword arguments of :func:`render_dvr_job` that the
    Render settings (``Scene.volumeevm_render``) ask for."""
    if volume_name:
        vol = bpy.data.objects.get(volume_name)
        if vol is None:
            raise VolumeEVMError(f"no object named {volume_name!r}")
    else:
        vol = render_volume(context, settings)
        if vol is None:
            raise VolumeEVMError("choose the volume to render (or select one)")
    vol = volume_object(vol)
    ensure_ramp(settings)
    tf = volume_transfer_function(settings, vol)
    return vol, tf, dict(
        method=settings.method, mode=settings.mode,
        options=settings_options(settings, vol, settings.method),
        image_name=settings.image_name or DEFAULT_IMAGE,
        exr_path=settings.exr_path if settings.use_exr else "",
        png_path=settings.png_path if settings.use_png else "",
        overwrite=settings.overwrite, hide_surface=settings.hide_surface)


def render_dvr(volume_obj, tf=None, *, scene=None, method="raycast", mode="over",
               options=None, camera_object=None, image_name=DEFAULT_IMAGE, exr_path="", png_path="",
               overwrite=False, hide_surface=True):
    """Render a volume object's VolumeEVM into the scene: scene pass, DVR, composite, image.

    Parameters
    ----------
    volume_obj : bpy.types.Object
        A volume object (or its surface) with a built VolumeEVM.
    tf : TransferFunction, optional
        Classification in the data's own units (``TransferFunction.preset(...)``, or
        :func:`.transfer.transfer_function` for the sidebar's colour ramp). Default: what the
        sidebar renders the volume with (:func:`.transfer.volume_transfer_function`: a label
        map's label colours, else the scene's colour ramp).
    scene : bpy.types.Scene, optional
        Default: the context's scene.
    method, mode : str
        As for the core's ``render`` (``"raycast"`` and ``"over"`` by default), or the method
        ``"gpu"`` (:func:`.gpu_draw.render_gpu`; the CPU ray caster where no GPU context can
        be made, said in the result's ``note``).
    options : dict, optional
        Method options (the core's ``method_options`` and ``render_options``, the GPU's too);
        ``level`` is ``"auto"`` unless given, as the Render setting Resolution is by default.
    camera_object : bpy.types.Object, optional
        Default: ``scene.camera``.
    image_name : str
        The composite's Image datablock; the volume alone goes to ``image_name + " DVR"``.
    exr_path, png_path : str
        Files to write ("" = none; ``//`` = beside the .blend, refused while it is not saved).
    overwrite : bool
        Replace existing files (default: refuse).
    hide_surface : bool
        Leave the volume's own surface mesh out of the scene pass (default True).

    Returns
    -------
    DVRResult
        Arrays, images and paths; ``visible`` is False if nothing of the volume was seen;
        ``note`` says when the GPU method fell back to the CPU, or drew a coarser level.

    Raises
    ------
    VolumeEVMError
        No camera, a bad tf or method, no VolumeEVM, a file that exists, a ``//`` path in an
        unsaved .blend (before the scene pass); a bad mode or option (the core's ``render``,
        after it).
    """
    scene = bpy.context.scene if scene is None else scene
    if tf is None:
        settings = scene.volumeevm_render
        ensure_ramp(settings)
        tf = volume_transfer_function(settings, volume_object(volume_obj))
    return jobs.run(render_dvr_job(
        scene, volume_obj, tf, method=method, mode=mode, options=options,
        camera_object=camera_object, image_name=image_name, exr_path=exr_path,
        png_path=png_path, overwrite=overwrite, hide_surface=hide_surface))


def render_dvr_animation(volume_obj, tf=None, *, scene=None, frames=None, exr_path="", png_path="",
                         overwrite=False, **options):
    """Render VolumeEVM for every frame: frame set, scene pass, DVR, composite, files.

    F12 animations cannot make a depth-correct DVR (the scene cannot be rendered again from
    inside its own render), so this loop renders each frame itself.

    Parameters
    ----------
    volume_obj, tf
        As for :func:`render_dvr`.
    scene : bpy.types.Scene, optional
    frames : iterable of int, optional
        Default: the scene's frame range and step.
    exr_path, png_path : str
        File name patterns; the last run of ``#`` becomes the frame number (see
        :func:`frame_path`). "" = no files.
    overwrite : bool
    **options
        Passed to :func:`render_dvr` (method, mode, options, camera_object, hide_surface...).

    Returns
    -------
    list of (int, DVRResult)
        The images hold the last frame; the scene is back at its current frame afterwards.

    Raises
    ------
    VolumeEVMError
        As :func:`render_dvr`, for the first frame that fails.
    """
    scene = bpy.context.scene if scene is None else scene
    if frames is None:
        frames = range(scene.frame_start, scene.frame_end + 1, scene.frame_step)
    frames = [int(f) for f in frames]
    current = scene.frame_current
    results = []
    try:
        for number, frame in enumerate(frames):
            if bpy.app.background:
                print(jobs.progress_line(number / max(len(frames), 1), f"frame {frame}"),
                      flush=True)
            scene.frame_set(frame)
            results.append((frame, render_dvr(
                volume_obj, tf, scene=scene, overwrite=overwrite,
                exr_path=frame_path(exr_path, frame) if exr_path else "",
                png_path=frame_path(png_path, frame) if png_path else "", **options)))
    finally:
        scene.frame_set(current)
    return results
