"""Blender side of the camera: build the core's :class:`Camera` record from a scene's camera.

The DVR job (:mod:`.dvr`) calls :func:`camera_from_blender`; the core never sees a Blender type.
"""

import numpy as np

from ..volumeevm_addon import Camera, VolumeEVMError


def camera_from_blender(scene, camera_object=None):
    """The :class:`Camera` that reproduces how ``scene`` renders through a camera object.

    Parameters
    ----------
    scene : bpy.types.Scene
        Supplies the render settings: resolution, percentage, pixel aspect.
    camera_object : bpy.types.Object, optional
        A camera object (default ``scene.camera``). Its current ``matrix_world`` and camera data
        are read (call ``view_layer.update()`` or ``frame_set`` first after changing them).

    Returns
    -------
    Camera
        Orthographic or perspective, with sensor fit, shift, clip range, resolution and pixel
        aspect copied from Blender.

    Raises
    ------
    VolumeEVMError
        No camera, an object that is not a camera, or a panoramic camera.
    """
    obj = scene.camera if camera_object is None else camera_object
    if obj is None:
        raise VolumeEVMError(f"scene {scene.name!r} has no camera; set scene.camera or pass one")
    if obj.type != "CAMERA":
        raise VolumeEVMError(f"camera_object: {obj.name!r} is a {obj.type}, not a CAMERA")
    cam = obj.data
    r = scene.render
    matrix = np.array([list(row) for row in obj.matrix_world], dtype=np.float64)
    common = dict(
        sensor_fit=cam.sensor_fit,
        shift_x=cam.shift_x,
        shift_y=cam.shift_y,
        clip_start=cam.clip_start,
        clip_end=cam.clip_end,
        resolution_x=r.resolution_x,
        resolution_y=r.resolution_y,
        resolution_percentage=r.resolution_percentage,
        pixel_aspect_x=r.pixel_aspect_x,
        pixel_aspect_y=r.pixel_aspect_y,
    )
    if cam.type == "ORTHO":
        return Camera.orthographic(matrix, cam.ortho_scale, **common)
    if cam.type == "PERSP":
        return Camera.perspective(matrix, cam.lens, sensor_width=cam.sensor_width,
                                  sensor_height=cam.sensor_height, **common)
    raise VolumeEVMError(
        f"camera_object: {obj.name!r} is a {cam.type} camera; only PERSP and ORTHO are supported")
