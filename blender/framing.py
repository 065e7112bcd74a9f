"""Framing a volume: a camera that shows the whole volume from a chosen side, and the objects
that enclose a volume and hide it (the default scene's 2 m cube around a 0.26 m scan).

:func:`frame_volume` places the scene's camera (made if the scene has none) on one side of the
volume, looking at its centre, at the distance (perspective) or scale (orthographic) at which
the sphere around the volume's box fits the image, and sets the clip range around that
sphere. :func:`enclosing_objects` finds visible meshes whose bounding box holds the whole
volume box; the scene pass renders them in front of the volume, so the DVR would be empty.
"""

import bpy
import numpy as np
from mathutils import Matrix

from ..volumeevm_addon import VolumeEVMError
from .camera import camera_from_blender
from .objects import volume_object

#: Sides a volume is framed from, as the 3D view's numpad views name them:
#: identifier -> (view direction, image up), world axes (LPS: +X left, +Y posterior, +Z up).
SIDES = {
    "FRONT": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "BACK": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "RIGHT": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "LEFT": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "TOP": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
    "BOTTOM": ((0.0, 0.0, 1.0), (0.0, -1.0, 0.0)),
}
#: The sphere around the volume box fills this fraction of the image's shorter side.
FILL = 0.9


def volume_corners(vol_obj):
    """The world positions (8, 3) of a volume object's box corners (its wire mesh's vertices)."""
    mesh = vol_obj.data
    co = np.empty(len(mesh.vertices) * 3, np.float64)
    mesh.vertices.foreach_get("co", co)
    matrix = np.array(vol_obj.matrix_world, np.float64)
    return co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]


def frame_volume(volume_obj, side="FRONT", *, scene=None, camera_object=None):
    """Place a camera so the whole volume is in its view, seen from ``side``.

    Parameters
    ----------
    volume_obj : bpy.types.Object
        A volume object (or its surface).
    side : str
        One of :data:`SIDES` ("FRONT" looks along +Y, as the 3D view's Front view).
    scene : bpy.types.Scene, optional
        Default: the context's scene.
    camera_object : bpy.types.Object, optional
        Default: the scene's camera; a new camera (made the scene's) when it has none.

    Returns
    -------
    bpy.types.Object
        The camera. Its lens (or type) stays; its shift becomes 0, its orthographic scale and
        clip range are set.

    Raises
    ------
    VolumeEVMError
        Not a volume, an unknown side, a camera object that is not a camera, a panoramic one.
    """
    vol_obj = volume_object(volume_obj)
    if side not in SIDES:
        raise VolumeEVMError(f"side must be one of {tuple(SIDES)}, got {side!r}")
    scene = bpy.context.scene if scene is None else scene
    cam = scene.camera if camera_object is None else camera_object
    if cam is None:
        cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
        scene.collection.objects.link(cam)
        scene.camera = cam
    if cam.type != "CAMERA":
        raise VolumeEVMError(f"camera_object: {cam.name!r} is a {cam.type}, not a CAMERA")
    corners = volume_corners(vol_obj)
    centre = (corners.min(axis=0) + corners.max(axis=0)) / 2
    radius = float(np.linalg.norm(corners - centre, axis=1).max()) or 1e-3
    forward, up = (np.array(v) for v in SIDES[side])
    right = np.cross(forward, up)
    data = cam.data
    data.shift_x = data.shift_y = 0.0
    # The view plane's half size: at unit distance (perspective) or in units (orthographic).
    half = min(np.abs(camera_from_blender(scene, cam).viewplane))
    if data.type == "ORTHO":
        data.ortho_scale *= radius / (half * FILL)
        distance = 2.0 * radius
    elif data.type == "PERSP":
        distance = radius / (FILL * np.sin(np.arctan(half)))
    else:
        raise VolumeEVMError(f"camera_object: {cam.name!r} is a {data.type} camera; only PERSP "
                             f"and ORTHO can frame a volume")
    data.clip_start = 0.5 * (distance - radius)
    data.clip_end = 2.0 * (distance + radius)
    matrix = np.identity(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = right, up, -forward
    matrix[:3, 3] = centre - distance * forward
    cam.matrix_world = Matrix(matrix.tolist())
    return cam


def enclosing_objects(volume_obj, scene=None):
    """The visible mesh objects of ``scene`` whose bounding box holds the whole volume box
    (the volume's own surface aside): the scene pass renders them in front of the volume."""
    vol_obj = volume_object(volume_obj)
    scene = bpy.context.scene if scene is None else scene
    corners = np.column_stack([volume_corners(vol_obj), np.ones(8)])
    found = []
    for obj in scene.objects:
        if (obj.type != "MESH" or obj.volumeevm.role != "NONE" or obj.hide_render
                or not obj.visible_get()):
            continue
        local = corners @ np.array(obj.matrix_world.inverted(), np.float64).T
        box = np.array([list(c) for c in obj.bound_box], np.float64)
        if np.all(local[:, :3] >= box.min(axis=0)) and np.all(local[:, :3] <= box.max(axis=0)):
            found.append(obj)
    return found


def hide_enclosing(volume_obj, scene=None):
    """Hide the objects that enclose the volume (:func:`enclosing_objects`) in the viewport
    and the render; returns them."""
    found = enclosing_objects(volume_obj, scene)
    for obj in found:
        obj.hide_set(True)
        obj.hide_render = True
    return found
