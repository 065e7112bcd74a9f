"""The scene pass: the scene rendered by its own engine, its colour and depth read back.

Render Result pixels cannot be read from Python, so the render is saved to a temporary
multilayer EXR and read back (``Combined`` RGBA and ``Depth`` Z of the rendered view layer), with
the Depth pass on and compositing off (the VolumeEVM compositor set-up must not feed back into
its own input). Every setting touched is put back afterwards (:func:`changed`).
"""

import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.rendering import BACKGROUND_DEPTH
from . import exr


@dataclass
class SceneRender:
    """The scene pass: ``rgba`` (H, W, 4) and ``depth`` (H, W), float32, row 0 at the top."""

    rgba: np.ndarray
    depth: np.ndarray


def render_layer(scene):
    """The view layer whose passes are read (the context's if it renders, else the first)."""
    layer = getattr(bpy.context, "view_layer", None)
    if layer is not None and scene.view_layers.get(layer.name) == layer and layer.use:
        return layer
    for layer in scene.view_layers:
        if layer.use:
            return layer
    raise VolumeEVMError(f"scene {scene.name!r}: no view layer is enabled for rendering")


@contextmanager
def changed(items):
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

    Raises
    ------
    VolumeEVMError
        No view layer renders, the engine fails (e.g. one that needs a GPU), a pass is missing.
    """
    layer = render_layer(scene)
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
        with changed(items):
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
