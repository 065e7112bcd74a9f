"""The DVR render job: the Blender scene, its depth pass, the core's volume render, the composite.

How one render goes (:func:`render_dvr_job`; the operator ``volumeevm.render_dvr`` and the
script function :func:`render_dvr` run the same job):

1. **Scene pass** (main thread): the scene is rendered by its own engine with the Depth pass on
   and compositing off (the VolumeEVM compositor set-up must not feed back into its own input);
   the volume's own surface mesh is hidden for it (the DVR shows the volume) unless asked not
   to. Render Result pixels cannot be read from Python, so the result is saved to a temporary
   multilayer EXR and read back (``Combined`` RGBA and ``Depth`` Z of the rendered view layer).
   Every setting touched is put back afterwards.
2. **Camera**: :func:`.camera.camera_from_blender` (the scene camera, or the one given).
3. **Volume render** (a worker thread in the UI): the core's ``render(vevm, camera, tf,
   method=, mode=, depth_in=scene_depth, matrix_world=volume.matrix_world, **options)``; rays
   stop at the scene's geometry. The VolumeEVM is the tool stack's result when the volume has
   tools. The Render setting Resolution (``level`` of :func:`method_options`, Auto by default)
   renders a volume much finer than the image's pixels from a coarser level of it.
4. **Composite** in NumPy, alpha over with premultiplied colour:
   ``out = dvr + (1 - dvr.a) · scene`` (all four channels). Output depth ``Z`` is the DVR's
   depth where the DVR is visible, else the scene's (axial, Blender units, 1e10 = nothing).
5. **Images and files** (main thread): two float Image datablocks (bottom row first, alpha
   premultiplied, scene-linear): ``<name>`` holds the composite and ``<name> DVR`` the volume
   alone (the compositor set-up lays that one over the Render Layers, :mod:`.render`). Optional
   EXR (R, G, B, A, Z) and PNG (the scene's view transform applied, as F12 saves it), both
   written atomically and never over an existing file unless ``overwrite``. All or nothing:
   if any part of this step (or the operator's report after it) fails, the images get their
   names, sizes and pixels back, new files are removed and replaced ones come back.

Script use::

    from bl_ext.user_default.volumeevm.operators import dvr
    result = dvr.render_dvr(volume_obj, tf=TransferFunction.preset("ct_bone"), method="raycast",
                            exr_path="/tmp/head.exr", png_path="/tmp/head.png")
    result.image, result.rgba, result.depth

Caveats: the Depth pass is one sample per pixel (not anti-aliased), so the edge of geometry in
front of the volume can show a one-pixel fringe; motion blur and panoramic cameras are not
supported; a render border is ignored (the whole frame is rendered).
"""

import functools
import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import (
    BACKGROUND_DEPTH,
    LEVELS,
    METHODS,
    MODES,
    TransferFunction,
    VolumeEVMError,
    atomic_target,
    render,
    write_atomically,
)
from . import _jobs, api, exr
from .camera import camera_from_blender

__all__ = ["render_dvr", "render_dvr_job", "render_dvr_animation", "view_signature",
           "frame_path", "render_scene", "composite_over", "output_depth", "volume_for_render",
           "put_image", "DVRResult", "SceneRender", "DEFAULT_IMAGE"]

#: Name of the composite Image datablock (the DVR alone is ``DEFAULT_IMAGE + " DVR"``).
DEFAULT_IMAGE = "VolumeEVM Render"


# ---------------------------------------------------------------------------- results
@dataclass
class SceneRender:
    """The scene pass: ``rgba`` (H, W, 4) and ``depth`` (H, W), float32, row 0 at the top."""

    rgba: np.ndarray
    depth: np.ndarray


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


# ---------------------------------------------------------------------------- pure parts
def composite_over(dvr_rgba, scene_rgba):
    """Premultiplied alpha over: ``dvr + (1 - dvr.a) · scene`` for all four channels.

    Parameters
    ----------
    dvr_rgba, scene_rgba : (H, W, 4) ndarray
        Premultiplied RGBA, same shape.

    Returns
    -------
    (H, W, 4) ndarray of np.float32
    """
    dvr = np.asarray(dvr_rgba, np.float32)
    scene = np.asarray(scene_rgba, np.float32)
    if dvr.shape != scene.shape or dvr.ndim != 3 or dvr.shape[2] != 4:
        raise VolumeEVMError(f"dvr_rgba {dvr.shape} and scene_rgba {scene.shape}: expected the "
                             f"same (H, W, 4) shape")
    return dvr + (1.0 - dvr[..., 3:4]) * scene


def output_depth(dvr_depth, scene_depth):
    """Depth of the composite: the DVR's where it saw something, else the scene's."""
    dvr_depth = np.asarray(dvr_depth, np.float32)
    return np.where(dvr_depth < BACKGROUND_DEPTH, dvr_depth,
                    np.asarray(scene_depth, np.float32)).astype(np.float32)


def method_options(method, quality, spacing, *, shading=False, termination=0.99, level="auto",
                   slices_per_voxel=1, classification="pre", jitter=False, preintegrate=False):
    """The core's options for one quality setting (1 = each method's default sampling).

    ``quality`` scales the sampling density: shear-warp's intermediate pixels per voxel
    (``intermediate_scale``), the ray casters' samples per voxel (``step_mm`` = half the
    smallest voxel size / quality), the reference's (smallest voxel size / 16 / quality).
    Splatting: ``quality`` rounded is its number of sub-slabs per sheet (``substeps``). ``level`` is the Render setting
    Resolution: ``"auto"`` (default) renders a volume much finer than the pixels from a coarser
    level, ``"full"`` every voxel (the core's ``render(level=...)``; the reference ignores it).
    The method's own settings go only to the method that has them: ``slices_per_voxel`` and
    ``classification`` to shear-warp, ``jitter`` and ``preintegrate`` to the ray casters.
    """
    quality = float(quality)
    if not np.isfinite(quality) or quality <= 0:
        raise VolumeEVMError(f"quality: must be > 0, got {quality!r}")
    if level not in LEVELS:
        raise VolumeEVMError(f"level: one of {LEVELS}, got {level!r}")
    smallest = float(min(spacing))
    options = {"termination": float(termination), "level": level}
    if shading:
        options["shading"] = True
    if method == "shear_warp":
        options.update(intermediate_scale=quality, slices_per_voxel=int(slices_per_voxel),
                       classification=classification)
    elif method == "splat":
        options["substeps"] = max(1, int(round(quality)))
    elif method in ("raycast", "raycast_navigate"):
        options.update(step_mm=0.5 * smallest / quality, jitter=bool(jitter),
                       preintegrate=bool(preintegrate))
    elif method == "reference":
        options = {k: v for k, v in options.items() if k != "termination"}
        options["step_mm"] = smallest / 16.0 / quality
    return options


# ---------------------------------------------------------------------------- Blender parts
def volume_for_render(vol_obj):
    """The VolumeEVM to render: the tool stack's result if the volume has tools, else its own."""
    vol_obj = api.volume_object(vol_obj)
    if len(vol_obj.volumeevm.tools):
        return api.evaluate(vol_obj)
    return api.get_vevm(vol_obj)


def _render_layer(scene):
    """The view layer whose passes are read (the context's if it renders, else the first)."""
    layer = getattr(bpy.context, "view_layer", None)
    if layer is not None and scene.view_layers.get(layer.name) == layer and layer.use:
        return layer
    for layer in scene.view_layers:
        if layer.use:
            return layer
    raise VolumeEVMError(f"scene {scene.name!r}: no view layer is enabled for rendering")


@contextmanager
def _changed(items):
    """Set ``(owner, attribute, value)`` items, then put the old values back.

    Old values go back in the same order (not reversed): an image format is restored before
    its colour depth, which the format would otherwise clamp (EXR has no 8 bits).
    """
    old = [(owner, name, getattr(owner, name)) for owner, name, _ in items]  # all first:
    try:  # setting one (5.x media_type) may change another (file_format)
        for owner, name, value in items:
            if getattr(owner, name) != value:
                setattr(owner, name, value)
        yield
    finally:
        for owner, name, value in old:
            if getattr(owner, name) != value:
                setattr(owner, name, value)


def render_scene(scene, *, camera_object=None, hide=()):
    """Render ``scene`` with its own engine and read Combined and Depth back.

    Parameters
    ----------
    scene : bpy.types.Scene
    camera_object : bpy.types.Object, optional
        Render through this camera (default: the scene's).
    hide : iterable of bpy.types.Object
        Objects left out of this render (e.g. the volume's surface mesh).

    Returns
    -------
    SceneRender
        Premultiplied scene-linear RGBA and axial depth (1e10 = background), row 0 at the top.
    """
    layer = _render_layer(scene)
    r = scene.render
    settings = r.image_settings
    items = [(layer, "use_pass_z", True), (r, "use_compositing", False),
             (r, "use_sequencer", False), (r, "use_border", False)]
    if camera_object is not None:
        items.append((scene, "camera", camera_object))
    items += [(obj, "hide_render", True) for obj in hide]
    if hasattr(settings, "media_type"):  # 5.x: multilayer is a media type
        items.append((settings, "media_type", "MULTI_LAYER_IMAGE"))
    items += [(settings, "file_format", "OPEN_EXR_MULTILAYER"), (settings, "color_depth", "32"),
              (settings, "exr_codec", "ZIP")]
    folder = Path(tempfile.mkdtemp(prefix="volumeevm-scene-"))
    path = folder / "scene.exr"
    try:
        with _changed(items):
            try:
                bpy.ops.render.render(scene=scene.name, layer=layer.name)
            except RuntimeError as error:  # e.g. an engine that needs a GPU, headless
                raise VolumeEVMError(f"scene render ({r.engine}) failed: {error}") from None
            result = bpy.data.images.get("Render Result")
            if result is None:
                raise VolumeEVMError(f"scene {scene.name!r}: the render produced no result")
            result.save_render(str(path), scene=scene)
        channels = exr.read_exr(path)
    finally:
        path.unlink(missing_ok=True)
        folder.rmdir()
    prefix = f"{layer.name}."
    try:
        rgba = np.stack([channels[f"{prefix}Combined.{c}"] for c in "RGBA"], axis=-1)
        depth = channels[f"{prefix}Depth.Z"]
    except KeyError as missing:
        raise VolumeEVMError(f"scene render: pass {missing} missing from the render result "
                             f"(engine {r.engine})") from None
    depth = np.where(np.isnan(depth), BACKGROUND_DEPTH, depth).astype(np.float32)
    return SceneRender(np.nan_to_num(rgba).astype(np.float32), depth)


def put_image(name, rgba):
    """Put a top-row-first premultiplied float RGBA array into an Image datablock.

    An existing generated float image of that name is reused (resized if needed), so the
    compositor's Image node keeps showing it; another image of that name is renamed away (and
    removed when unused). In a :func:`._jobs.transaction` that fails, the images get their
    names, sizes and pixels back.

    Returns
    -------
    bpy.types.Image
    """
    rgba = np.asarray(rgba, np.float32)
    h, w = rgba.shape[:2]
    image = bpy.data.images.get(name)
    if image is not None and image.is_float and image.source == "GENERATED":
        _jobs.on_undo(functools.partial(_put_back_pixels, image, tuple(image.size),
                                        _pixels(image)))
        if tuple(image.size) != (w, h):
            image.scale(w, h)  # in place: the compositor's Image node keeps pointing at it
    elif image is not None:  # another kind of image: it makes way (removed if unused)
        _jobs.on_undo(functools.partial(_give_name_back, image, name))
        _jobs.on_success(functools.partial(_remove_unused_image, image))
        image.name = f"{name} (old)"
        image = None
    if image is None:
        image = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    _jobs.assign(image, alpha_mode="PREMUL")
    image.pixels.foreach_set(np.ascontiguousarray(np.flipud(rgba)).ravel())
    image.update()
    return image


def _pixels(image):
    pixels = np.empty(len(image.pixels), np.float32)
    image.pixels.foreach_get(pixels)
    return pixels


def _put_back_pixels(image, size, pixels):
    """Undo :func:`put_image` on a reused image: its old size and pixels."""
    if tuple(image.size) != size:
        image.scale(*size)
    image.pixels.foreach_set(pixels)
    image.update()


def _give_name_back(image, name):
    """Undo :func:`put_image` making way: ``image`` gets its name back from the failed job's
    image (which the transaction removes afterwards)."""
    taken = bpy.data.images.get(name)
    if taken is not None:
        taken.name = f"{name} (failed)"
    image.name = name


def _remove_unused_image(image):
    if image.users == 0:
        bpy.data.images.remove(image)


def _set_property(block, key, value):
    """Set a custom property of a datablock; put back (or removed) if the transaction fails."""
    if key in block:
        _jobs.on_undo(functools.partial(block.__setitem__, key, block[key]))
    else:
        _jobs.on_undo(functools.partial(block.pop, key))
    block[key] = value


def _write_file(path, write, *, overwrite):
    """Write a file with ``write()`` (atomic, never over a file unless ``overwrite``), undone
    if the transaction fails: a new file is removed again, a replaced one comes back.

    The replaced file is kept as a hard link (a copy where the file system has none) in a
    hidden folder beside it until the job succeeded. Returns what ``write`` returns.
    """
    path = Path(path)
    kept = None
    if overwrite and path.exists():
        try:
            folder = Path(tempfile.mkdtemp(prefix=".volumeevm-old-", dir=path.parent))
            kept = folder / path.name
            try:
                os.link(path, kept)
            except OSError:  # no hard links on this file system
                shutil.copy2(path, kept)
        except OSError as error:
            if kept is not None:
                _drop_kept(kept)
            raise VolumeEVMError(f"{path}: cannot keep the old file while the new one is "
                                 f"written ({error.strerror or error})") from error
    try:
        written = write()
    except BaseException:
        if kept is not None:
            _drop_kept(kept)
        raise
    if kept is None:
        _jobs.on_undo(functools.partial(path.unlink, missing_ok=True))
    else:
        _jobs.on_undo(functools.partial(_restore_kept, kept, path))
        _jobs.on_success(functools.partial(_drop_kept, kept))
    return written


def _restore_kept(kept, path):
    os.replace(kept, path)
    kept.parent.rmdir()


def _drop_kept(kept):
    kept.unlink(missing_ok=True)
    kept.parent.rmdir()


def write_png(image, path, scene, *, overwrite=False):
    """Save an Image as PNG through the scene's colour management (what F12 would save)."""
    settings = scene.render.image_settings
    items = []
    if hasattr(settings, "media_type"):
        items.append((settings, "media_type", "IMAGE"))
    items += [(settings, "file_format", "PNG"), (settings, "color_mode", "RGBA"),
              (settings, "color_depth", "8")]

    def save(temporary):
        with _changed(items):
            image.save_render(str(temporary), scene=scene)

    return write_atomically(path, save, overwrite=overwrite)


#: Custom property of the DVR image: the view it was rendered for (see :func:`view_signature`).
VIEW_KEY = "volumeevm_view"


def view_signature(scene, camera_object=None):
    """A string naming what a DVR image depends on besides the volume: frame, camera (placement
    and lens), resolution. The compositor's render_pre check compares it (``render.py``)."""
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


def _abspath(path):
    return str(Path(bpy.path.abspath(path))) if path else ""


def render_dvr_job(scene, volume_obj, tf, *, method="raycast", mode="over", options=None,
                   camera_object=None, image_name=DEFAULT_IMAGE, exr_path="", png_path="",
                   overwrite=False, hide_surface=True):
    """The DVR job (see :func:`render_dvr`). The scene pass runs here, on the calling thread."""
    if method not in METHODS:
        raise VolumeEVMError(f"method must be one of {METHODS}, got {method!r}")
    if mode not in MODES:
        raise VolumeEVMError(f"mode must be one of {MODES}, got {mode!r}")
    if not isinstance(tf, TransferFunction):
        raise VolumeEVMError(f"tf: expected a TransferFunction, got {type(tf).__name__}")
    vol_obj = api.volume_object(volume_obj)
    _render_layer(scene).update()  # placements changed since the last update (scripts)
    camera = camera_from_blender(scene, camera_object)
    exr_path, png_path = _abspath(exr_path), _abspath(png_path)
    for path in (exr_path, png_path):
        if path:
            atomic_target(path, overwrite=overwrite)  # fail before the slow part
    vevm = volume_for_render(vol_obj)
    matrix_world = np.array(vol_obj.matrix_world, np.float64)
    hide = []
    if hide_surface:
        surface = api.own_surface(vol_obj)
        if surface is not None:
            hide.append(surface)
    if bpy.app.background:
        print(_jobs.progress_line(0.0, f"rendering scene {scene.name!r} ({scene.render.engine})"),
              flush=True)
    scene_pass = render_scene(scene, camera_object=camera_object, hide=hide)
    if scene_pass.depth.shape != camera.shape:
        raise VolumeEVMError(f"scene render is {scene_pass.depth.shape[::-1]} pixels, the camera "
                             f"{camera.shape[::-1]}")
    options = {"level": "auto", **(options or {})}  # the Render setting Resolution's default
    signature = view_signature(scene, camera_object)

    def steps():
        yield 0.2, f"volume render ({method}, {mode})"
        dvr_rgba, dvr_depth = render(vevm, camera, tf, method=method, mode=mode,
                                     depth_in=scene_pass.depth, matrix_world=matrix_world,
                                     **options)
        yield 0.9, "compositing"
        dvr_rgba = np.nan_to_num(np.asarray(dvr_rgba, np.float32))
        rgba = composite_over(dvr_rgba, scene_pass.rgba)
        depth = output_depth(dvr_depth, scene_pass.depth)
        return DVRResult(rgba, depth, dvr_rgba, np.asarray(dvr_depth, np.float32), scene_pass,
                         visible=bool((dvr_rgba[..., 3] > 0).any()))

    def commit(result):  # all undone if it (or the operator's report) fails
        result.image = put_image(image_name, result.rgba)
        result.dvr_image = put_image(f"{image_name} DVR", result.dvr_rgba)
        _set_property(result.dvr_image, VIEW_KEY, signature)
        if exr_path:
            result.exr_path = str(_write_file(exr_path, functools.partial(
                exr.write_exr, exr_path, result.rgba, result.depth, overwrite=overwrite),
                overwrite=overwrite))
        if png_path:
            result.png_path = str(_write_file(png_path, functools.partial(
                write_png, result.image, png_path, scene, overwrite=overwrite),
                overwrite=overwrite))
        return result

    return _jobs.Job(f"Render {vol_obj.name}", steps(), commit)


def render_dvr(volume_obj, tf, *, scene=None, method="raycast", mode="over", options=None,
               camera_object=None, image_name=DEFAULT_IMAGE, exr_path="", png_path="",
               overwrite=False, hide_surface=True):
    """Render a volume object's VolumeEVM into the scene: scene pass, DVR, composite, image.

    Parameters
    ----------
    volume_obj : bpy.types.Object
        A volume object (or its surface) with a built VolumeEVM.
    tf : TransferFunction
        Classification in the data's own units (``TransferFunction.preset(...)``, or
        :func:`..ui.render_panel.transfer_function` for the sidebar's colour ramp).
    scene : bpy.types.Scene, optional
        Default: the context's scene.
    method, mode : str
        As for the core's ``render`` (``"raycast"`` and ``"over"`` by default).
    options : dict, optional
        Method options (see :func:`method_options`); ``level`` is ``"auto"`` unless given, as
        the Render setting Resolution is by default.
    camera_object : bpy.types.Object, optional
        Default: ``scene.camera``.
    image_name : str
        The composite's Image datablock; the volume alone goes to ``image_name + " DVR"``.
    exr_path, png_path : str
        Files to write ("" = none; ``//`` = beside the .blend).
    overwrite : bool
        Replace existing files (default: refuse).
    hide_surface : bool
        Leave the volume's own surface mesh out of the scene pass (default True).

    Returns
    -------
    DVRResult
        Arrays, images and paths; ``visible`` is False if nothing of the volume was seen.

    Raises
    ------
    VolumeEVMError
        No camera, a bad method/mode/tf, no VolumeEVM, a file that exists.
    """
    scene = bpy.context.scene if scene is None else scene
    return _jobs.run(render_dvr_job(
        scene, volume_obj, tf, method=method, mode=mode, options=options,
        camera_object=camera_object, image_name=image_name, exr_path=exr_path,
        png_path=png_path, overwrite=overwrite, hide_surface=hide_surface))


def render_dvr_animation(volume_obj, tf, *, scene=None, frames=None, exr_path="", png_path="",
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
                print(_jobs.progress_line(number / max(len(frames), 1), f"frame {frame}"),
                      flush=True)
            scene.frame_set(frame)
            results.append((frame, render_dvr(
                volume_obj, tf, scene=scene, overwrite=overwrite,
                exr_path=frame_path(exr_path, frame) if exr_path else "",
                png_path=frame_path(png_path, frame) if png_path else "", **options)))
    finally:
        scene.frame_set(current)
    return results
