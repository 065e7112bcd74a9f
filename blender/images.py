"""The DVR's outputs: float Image datablocks and image files, each undone if the job fails.

Inside a job's :func:`.jobs.transaction`, :func:`put_image` registers how to give an image its
name, size and pixels back, and :func:`write_file` how to remove a new file or bring a replaced
one back, so a render whose commit (or report) fails leaves images and files as they were.
"""

import functools
import os
import shutil
import tempfile
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.system import write_atomically
from . import jobs
from .scene import changed


# ---------------------------------------------------------------------------- Image datablocks
def put_image(name, rgba):
    """Put a top-row-first premultiplied float RGBA array into an Image datablock.

    An existing generated float image of that name is reused (resized if needed), so the
    compositor's Image node keeps showing it; another image of that name is renamed away (and
    removed when unused). In a :func:`.jobs.transaction` that fails, the images get their
    names, sizes and pixels back.

    Returns
    -------
    bpy.types.Image
    """
    rgba = np.asarray(rgba, np.float32)
    h, w = rgba.shape[:2]
    image = bpy.data.images.get(name)
    if image is not None and image.is_float and image.source == "GENERATED":
        jobs.on_undo(functools.partial(_put_back_pixels, image, tuple(image.size),
                                       _pixels(image)))
        if tuple(image.size) != (w, h):
            image.scale(w, h)  # in place: the compositor's Image node keeps pointing at it
    elif image is not None:  # another kind of image: it makes way (removed if unused)
        jobs.on_undo(functools.partial(_give_name_back, image, name))
        jobs.on_success(functools.partial(_remove_unused_image, image))
        image.name = f"{name} (old)"
        image = None
    if image is None:
        image = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    jobs.assign(image, alpha_mode="PREMUL")
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


# ---------------------------------------------------------------------------- files
def write_png(image, path, scene, *, overwrite=False):
    """Save an Image as PNG through the scene's colour management (what F12 would save)."""
    settings = scene.render.image_settings
    items = []
    if hasattr(settings, "media_type"):
        items.append((settings, "media_type", "IMAGE"))
    items += [(settings, "file_format", "PNG"), (settings, "color_mode", "RGBA"),
              (settings, "color_depth", "8")]

    def save(temporary):
        with changed(items):
            image.save_render(str(temporary), scene=scene)

    return write_atomically(path, save, overwrite=overwrite)


def write_file(path, write, *, overwrite):
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
        jobs.on_undo(functools.partial(path.unlink, missing_ok=True))
    else:
        jobs.on_undo(functools.partial(_restore_kept, kept, path))
        jobs.on_success(functools.partial(_drop_kept, kept))
    return written


def _restore_kept(kept, path):
    os.replace(kept, path)
    kept.parent.rmdir()


def _drop_kept(kept):
    kept.unlink(missing_ok=True)
    kept.parent.rmdir()
