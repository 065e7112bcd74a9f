"""The viewport's preview while an OME-Zarr level builds: the coarsest level's surface edges.

A build of a store's finer level first builds the coarsest level (small: the import already
read it) and hands its surface's edges to the running job (:func:`.jobs.show_preview`). A
``POST_VIEW`` draw handler draws them as lines, in the volume object's space, until the job ends
(finished, cancelled or failed): nothing is written into the scene, so a cancelled build leaves
nothing behind. Scripts and ``--background`` have no viewport: no preview is built there.
"""

from dataclasses import dataclass

import bpy
import gpu
import numpy as np
from gpu_extras.batch import batch_for_shader

from . import jobs
from .handlers import ViewportDraw

#: The preview lines' colour (RGBA, linear).
COLOR = (1.0, 0.55, 0.1, 1.0)

_batch = []  # [(preview, batch)] of the preview drawn last


@dataclass(frozen=True, eq=False)
class Preview:
    """A coarse level's surface edges, drawn while a finer level of the same store builds.

    Attributes
    ----------
    name : str
        The volume object the edges belong to (its space).
    level : int
        The store's level they were built from.
    co : (n, 3) ndarray of np.float32
        Vertices in Blender units, the volume object's space.
    edges : (e, 2) ndarray of np.int32
        The surface's edges, each once.
    """

    name: str
    level: int
    co: np.ndarray
    edges: np.ndarray


def current():
    """The preview of the running job, or None."""
    job = jobs.CURRENT
    return None if job is None else job.preview


def draw():
    """Draw the running job's preview over the bound framebuffer (the viewport's, or a test's
    offscreen) with the current view and projection matrices."""
    preview = current()
    if preview is None:
        _batch.clear()
        return
    obj = bpy.data.objects.get(preview.name)
    if obj is None:
        return
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    if not _batch or _batch[0][0] is not preview:
        _batch[:] = [(preview, batch_for_shader(shader, "LINES", {"pos": preview.co},
                                                indices=preview.edges))]
    with gpu.matrix.push_pop():
        gpu.matrix.multiply_matrix(obj.matrix_world)
        gpu.state.depth_test_set("LESS_EQUAL")
        shader.uniform_float("color", COLOR)
        _batch[0][1].draw(shader)
        gpu.state.depth_test_set("NONE")


_drawing = ViewportDraw(draw)


def register():
    """Add the preview's draw handler to every 3D viewport."""
    _drawing.add()


def unregister():
    """Remove the draw handler and drop the preview's batch."""
    _drawing.remove()
    _batch.clear()
