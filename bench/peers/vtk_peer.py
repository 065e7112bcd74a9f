"""VTK's CPU ray caster (``vtkFixedPointVolumeRayCastMapper``, PyPI ``vtk``) as a benchmark peer.

:func:`render` runs this file as a subprocess (so that its peak memory is its own): the scene goes
in as an ``.npz``, the image and times come back as an ``.npz``. The render window is offscreen
(``vtkEGLRenderWindow`` on Mesa when there is no X display; whatever VTK picks otherwise).

How the scene is matched
------------------------
- **Volume**: ``vtkImageData`` in millimetres with the densities (x fastest); point ``(i, j, k)``
  at ``origin + (i, j, k)·spacing`` where ``origin`` is the position of **our voxel (0, 0, 0)'s
  centre**. VTK's samples sit on the points (box corners of its cells) while ours are cell
  centres: placing VTK's point lattice on our voxel centres is the half-voxel shift. VTK's volume
  then ends at the outermost voxel centres, half a voxel inside our box (whose outer half-voxel
  shell repeats the boundary voxels, clamp-to-edge); both volumes here have (nearly) transparent
  borders, so this changes little. Only axis-aligned grids (identity orientation) are handled.
- **Transfer function**: ``vtkColorTransferFunction`` (RGB points) and ``vtkPiecewiseFunction``
  (opacity points) at our control points (constant beyond the ends, as ours),
  ``SetScalarOpacityUnitDistance(unit_length_mm)``, linear interpolation, no shading.
- **Sampling**: ``AutoAdjustSampleDistances`` off (otherwise VTK lowers quality to reach a frame
  rate), ``SampleDistance`` in mm (VTK's default 1.0), ``ImageSampleDistance`` 1 (one ray per
  pixel), all threads.
- **View**: ``vtkCamera`` at our camera's position (mm), looking along our view axis with our up
  vector. Orthographic: parallel projection, parallel scale = half the view plane's height (for a
  square image ``ortho_scale / 2``). Perspective: view angle = the vertical field of view
  ``2·atan(ymax)`` of our view plane at unit distance. Clipping range around the volume.
- **Image**: VTK composites its premultiplied ray colours over the background. It is rendered over
  black and over white and read back as 8-bit RGB: over black gives the premultiplied colour
  ``C``; over white gives ``C + (1 - A)``, so ``A = 1 - mean_rgb(white - black)``. Rows are
  flipped (VTK's image row 0 is the bottom). Only the render over black is timed.
"""

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _rss_kb():
    """Peak resident set of this process (kB): VmHWM. getrusage's ru_maxrss is not used: on
    Linux it keeps the parent's (the bench's) peak across fork and exec."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def camera_params(camera, grid_to_world, shape, mm_per_unit):
    """Our Camera as vtkCamera parameters in millimetres."""
    g = np.asarray(grid_to_world, dtype=np.float64)
    if not np.allclose(g[:3, :3], np.diag(np.diag(g[:3, :3]))):
        raise ValueError("VTK peer: only axis-aligned grids")
    pos = camera.position * mm_per_unit
    fwd = camera.forward
    n = np.asarray(shape, dtype=np.float64)
    corners = np.array([[a, b, c, 1.0] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                        for c in (-0.5, n[2] - 0.5)]) @ g.T
    depth = camera.axial_depth(corners[:, :3]) * mm_per_unit
    near = max(depth.min() - 1.0, 1e-3 if not camera.is_ortho else depth.min() - 1.0)
    far = depth.max() + 1.0
    xmin, xmax, ymin, ymax = camera.viewplane
    if abs(xmin + xmax) > 1e-12 * abs(xmax) or abs(ymin + ymax) > 1e-12 * abs(ymax):
        raise ValueError("VTK peer: lens shift is not handled")
    return {
        "position": pos, "focal_point": pos + fwd * 0.5 * (near + far),
        "view_up": camera.up, "parallel": bool(camera.is_ortho),
        "parallel_scale": 0.5 * (ymax - ymin) * mm_per_unit,
        "view_angle": float(np.degrees(2.0 * np.arctan(ymax))) if not camera.is_ortho else 30.0,
        "clipping": (near, far), "size": (camera.width, camera.height),
    }


def render(densities, grid_to_world, camera, tf, *, mm_per_unit, frames=5, sample_distance=1.0,
           python=sys.executable, timeout=1800):
    """Render with VTK in a subprocess; returns a dict with ``rgba`` (H, W, 4) premultiplied
    float32, row 0 at the top, ``frames_s``, ``best_s``, ``max_rss_kb``, ``rss_before_data_kb``,
    ``window`` (the render window class) and ``vtk_version``."""
    g = np.asarray(grid_to_world, dtype=np.float64)
    cam = camera_params(camera, g, np.shape(densities), mm_per_unit)
    origin_mm = g[:3, 3] * mm_per_unit
    spacing_mm = np.diag(g[:3, :3]) * mm_per_unit
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "scene.npz"
        dst = Path(tmp) / "image.npz"
        np.savez(src, densities=np.asarray(densities), origin=origin_mm, spacing=spacing_mm,
                 tf_points=np.asarray(tf.points), unit_length_mm=tf.unit_length_mm,
                 frames=int(frames), sample_distance=float(sample_distance),
                 camera=json.dumps({k: (np.asarray(v).tolist() if isinstance(v, np.ndarray)
                                        else v) for k, v in cam.items()}))
        env = dict(os.environ)
        env.pop("DISPLAY", None)  # offscreen: EGL, no X server needed
        proc = subprocess.run([python, __file__, str(src), str(dst)], capture_output=True,
                              text=True, env=env, timeout=timeout, check=False)
        if proc.returncode != 0 or not dst.exists():
            raise RuntimeError(f"VTK peer failed ({proc.returncode}): {proc.stderr[-2000:]}")
        out = np.load(dst, allow_pickle=False)
        info = json.loads(str(out["info"]))
        info["rgba"] = out["rgba"]
    return info


def _main(src, dst):
    rss0 = _rss_kb()
    import vtk
    from vtk.util import numpy_support

    rss_vtk = _rss_kb()
    scene = np.load(src, allow_pickle=False)
    dens = scene["densities"]
    cam = json.loads(str(scene["camera"]))
    w, h = cam["size"]

    image = vtk.vtkImageData()
    image.SetDimensions(*dens.shape)
    image.SetOrigin(*scene["origin"])
    image.SetSpacing(*scene["spacing"])
    flat = np.ascontiguousarray(dens.T).ravel()  # x fastest
    arr = numpy_support.numpy_to_vtk(flat, deep=True)
    arr.SetName("density")
    image.GetPointData().SetScalars(arr)

    pts = scene["tf_points"]
    color = vtk.vtkColorTransferFunction()
    opacity = vtk.vtkPiecewiseFunction()
    for value, r, g_, b, a in pts:
        color.AddRGBPoint(float(value), float(r), float(g_), float(b))
        opacity.AddPoint(float(value), float(a))
    color.ClampingOn()
    opacity.ClampingOn()
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(color)
    prop.SetScalarOpacity(opacity)
    prop.SetScalarOpacityUnitDistance(float(scene["unit_length_mm"]))
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOff()

    mapper = vtk.vtkFixedPointVolumeRayCastMapper()
    mapper.SetInputData(image)
    mapper.SetAutoAdjustSampleDistances(0)
    mapper.SetLockSampleDistanceToInputSpacing(0)
    mapper.SetSampleDistance(float(scene["sample_distance"]))
    mapper.SetImageSampleDistance(1.0)
    mapper.SetBlendModeToComposite()
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)

    renderer = vtk.vtkRenderer()
    renderer.AddVolume(volume)
    renderer.SetBackground(0.0, 0.0, 0.0)
    window = None
    try:  # no X server: EGL directly (the generic factory tries X first and warns)
        from vtkmodules.vtkRenderingOpenGL2 import vtkEGLRenderWindow
        if not os.environ.get("DISPLAY"):
            window = vtkEGLRenderWindow()
    except ImportError:
        pass
    if window is None:
        window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    window.SetMultiSamples(0)
    window.AddRenderer(renderer)
    window.SetSize(w, h)

    vc = renderer.GetActiveCamera()
    vc.SetPosition(*cam["position"])
    vc.SetFocalPoint(*cam["focal_point"])
    vc.SetViewUp(*cam["view_up"])
    if cam["parallel"]:
        vc.ParallelProjectionOn()
        vc.SetParallelScale(cam["parallel_scale"])
    else:
        vc.ParallelProjectionOff()
        vc.SetViewAngle(cam["view_angle"])
    vc.SetClippingRange(*cam["clipping"])

    def grab():
        grabber = vtk.vtkWindowToImageFilter()
        grabber.SetInput(window)
        grabber.SetInputBufferTypeToRGB()
        grabber.ReadFrontBufferOff()
        grabber.Update()
        out = grabber.GetOutput()
        px = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars())
        return px.reshape(h, w, 3)[::-1].astype(np.float32) / 255.0

    window.Render()  # warm-up: builds the mapper's tables
    times = []
    for _ in range(int(scene["frames"])):
        t0 = time.perf_counter()
        window.Render()
        times.append(time.perf_counter() - t0)
    black = grab()
    renderer.SetBackground(1.0, 1.0, 1.0)
    window.Render()
    white = grab()
    alpha = np.clip(1.0 - (white - black).mean(axis=2), 0.0, 1.0)
    rgba = np.concatenate([black, alpha[..., None]], axis=2).astype(np.float32)
    info = {"frames_s": times, "best_s": min(times), "max_rss_kb": _rss_kb(),
            "rss_before_data_kb": rss_vtk, "rss_python_kb": rss0,
            "window": window.GetClassName(), "vtk_version": vtk.vtkVersion.GetVTKVersion(),
            "threads": mapper.GetNumberOfThreads(),
            "sample_distance_mm": mapper.GetSampleDistance()}
    np.savez(dst, rgba=rgba, info=json.dumps(info))


if __name__ == "__main__":
    _main(sys.argv[1], sys.argv[2])
