"""Render the GPU test cases in a Blender process of their own and save the images.

Run by ``test_gpu_render.py`` with the interpreter of the bpy line under test::

    python tests/gpu_runner.py OUT.npz DATA_DIR

It makes a GPU context (:func:`blender.gpu_context.ensure_context`), renders every case of
:data:`gpu_cases.CASES` with the GPU method and saves ``<case>_rgba`` and ``<case>_depth``, plus
``meta`` (JSON): whether a context was made (and why not), the GPU, each case's error and time,
and whether drawing put the GPU state back; the CT head drawn as a viewport draws it at rest
and moving (``resting_rgba``, ``moving_rgba``, their options and levels in ``meta``). Then the
extension is registered and Render VolumeEVM's job renders a scene with the GPU method, the CPU
ray caster, the GPU's fallback and the GPU at level 2 (``scene_*`` arrays, the notes in
``meta``); the viewport's drawing goes over Blender's Solid drawing of that scene
(``viewport_*`` arrays, the VolumeEVM in ``OUT.vevm``), and the draw handler's drawing draws it
while the view moves and rests (``handler_*`` arrays). A crash or a missing context here fails
or skips the GPU tests, never the rest of the suite.
"""

import importlib
import json
import sys
import time
import traceback
from pathlib import Path

TESTS = Path(__file__).resolve().parent
sys.path[:0] = [str(TESTS.parent), str(TESTS)]

import bpy  # noqa: E402
import gpu  # noqa: E402
import numpy as np  # noqa: E402

import gpu_cases  # noqa: E402
from sample_blends.make_demo import load_extension  # noqa: E402


def state():
    return gpu.state.blend_get(), gpu.state.depth_test_get(), gpu.state.depth_mask_get()


def state_restored(gpu_draw, data_dir):
    """Draw with a state unlike the draw's own set; is it the same afterwards?"""
    vevm, cam, tf, options = gpu_cases.case("irregular_over_ortho", data_dir)
    gpu.state.blend_set("ADDITIVE")
    gpu.state.depth_test_set("LESS_EQUAL")
    gpu.state.depth_mask_set(True)
    before = state()
    gpu_draw.render_gpu(vevm, cam, tf, **options)
    after = state()
    gpu.state.blend_set("NONE")
    gpu.state.depth_test_set("NONE")
    gpu.state.depth_mask_set(False)
    return before == after and before[0] == "ADDITIVE"


def moving(gpu_draw, arrays, data_dir):
    """The CT head drawn by the viewport's drawing (``gpu_viewport.draw_volume``, over an empty
    offscreen) with its options at rest and while the view moves (``draw_options``), and
    rendered at level 2: saves ``resting_rgba`` and ``moving_rgba``; returns both options
    and the levels drawn."""
    from volumeevm.blender import gpu_viewport

    vevm, cam, tf, options = gpu_cases.case("head_persp", data_dir)
    resting = {**options, "step_mm": gpu_cases.HEAD_STEP_MM}
    fast = gpu_viewport.draw_options(resting, True)
    h, w = cam.shape
    projection, view = cam.matrix_projection(), np.linalg.inv(cam.matrix_world)
    offscreen = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
    levels = []
    try:
        with offscreen.bind():
            framebuffer = gpu.state.active_framebuffer_get()
            for name, drawn in (("resting", resting), ("moving", fast)):
                framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
                levels.append(gpu_viewport.draw_volume(vevm, tf, projection, view, (w, h),
                                                       **drawn))
                rgba = np.empty((h, w, 4), np.float32)
                framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT",
                                       data=gpu.types.Buffer("FLOAT", rgba.size, rgba))
                arrays[f"{name}_rgba"] = np.flipud(rgba)
    finally:
        offscreen.free()
    *_, coarse = gpu_draw.render_gpu(vevm, cam, tf, **resting, level=2)
    return {"resting": resting, "moving": fast, "levels": [*levels, coarse]}


def scene_renders(ext, arrays, out):
    """Render VolumeEVM's job with the method "gpu" and with "raycast" (the same options) over
    a Cycles scene with a plane in front of part of the skull, and with the GPU unavailable
    (the fallback): saves ``scene_<what>_<name>`` arrays, returns the fallback's note."""
    import math

    from volumeevm.blender import api, dvr, gpu_context
    from volumeevm.volumeevm_addon import TransferFunction

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    vol = api.import_volume(TESTS.parent / "sample_blends" / "data" / "ct_skull_cgal.npy")
    api.build(vol, 2.9)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    cam.location = (0.124, -0.6, 0.115)
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)
    cam.data.clip_start, cam.data.clip_end = 0.01, 10.0
    scene.camera = cam
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 1
    scene.cycles.filter_width = 0.01
    scene.render.resolution_x, scene.render.resolution_y = 64, 48
    scene.render.film_transparent = True
    mesh = bpy.data.meshes.new("Plane")
    mesh.from_pydata([(-0.1, -0.1, 0), (0.1, -0.1, 0), (0.1, 0.1, 0), (-0.1, 0.1, 0)], [],
                     [(0, 1, 2, 3)])
    plane = bpy.data.objects.new("Plane", mesh)
    plane.location, plane.rotation_euler = (0.02, -0.2, 0.115), (math.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(plane)
    tf = TransferFunction(gpu_cases.SKULL_TF)  # the extension's own class: the job checks it
    options = {"step_mm": 0.25, "termination": 1.0, "level": "full"}
    results = {"gpu": dvr.render_dvr(vol, tf, method="gpu", options=options),
               "raycast": dvr.render_dvr(vol, tf, method="raycast", options=options)}
    ensure = gpu_context.ensure_context

    def unavailable():
        raise gpu_context.GPUUnavailable("no GPU context (simulated)")

    gpu_context.ensure_context = unavailable
    try:
        results["fallback"] = dvr.render_dvr(vol, tf, method="gpu", options=options)
    finally:
        gpu_context.ensure_context = ensure
    results["level"] = dvr.render_dvr(vol, tf, method="gpu", options={**options, "level": 2})
    for name, result in results.items():
        for what in ("rgba", "depth", "dvr_rgba", "dvr_depth"):
            arrays[f"scene_{what}_{name}"] = getattr(result, what)
    arrays["scene_depth_in"] = results["gpu"].scene.depth
    arrays["scene_colour_in"] = results["gpu"].scene.rgba
    viewport(vol, tf, options, arrays, out)
    viewport_handler(vol, arrays)
    return {name: result.note for name, result in results.items()}


def viewport(vol, tf, options, arrays, out):
    """The viewport's drawing over Blender's own Solid drawing of the same scene (offscreen
    ``draw_view3d`` with the scene camera's matrices): saves the Solid image and depth, the
    composite, the matrices and the VolumeEVM (``<out>.vevm``) for the reference."""
    from mathutils import Matrix
    from volumeevm.blender import api, display_lut, gpu_viewport
    from volumeevm.blender.camera import camera_from_blender

    scene = bpy.context.scene
    area = next(a for a in bpy.data.screens["Layout"].areas if a.type == "VIEW_3D")
    space = area.spaces.active
    space.shading.type = "SOLID"
    space.overlay.show_overlays = False  # the grid and the volume's wire box write depth here
    region = next(r for r in area.regions if r.type == "WINDOW")
    camera = camera_from_blender(scene)
    projection = camera.matrix_projection()
    view = np.linalg.inv(camera.matrix_world)
    h, w = camera.shape
    offscreen = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
    offscreen.draw_view3d(scene, bpy.context.view_layer, space, region, Matrix(view.tolist()),
                          Matrix(projection.tolist()))
    solid = np.empty((h, w, 4), np.float32)
    window = np.empty((h, w), np.float32)
    composite = np.empty((h, w, 4), np.float32)
    with offscreen.bind():
        framebuffer = gpu.state.active_framebuffer_get()
        framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT",
                               data=gpu.types.Buffer("FLOAT", solid.size, solid))
        framebuffer.read_depth(0, 0, w, h, data=gpu.types.Buffer("FLOAT", window.size, window))
        gpu_viewport.draw_volume(api.get_vevm(vol), tf, projection, view, (w, h),
                                 matrix_world=np.array(vol.matrix_world), **options)
        framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT",
                               data=gpu.types.Buffer("FLOAT", composite.size, composite))
        for table in (None, display_lut.srgb_table()):  # scene-linear, for an sRGB display
            alone = np.empty((h, w, 4), np.float32)
            framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
            gpu_viewport.draw_volume(api.get_vevm(vol), tf, projection, view, (w, h),
                                     matrix_world=np.array(vol.matrix_world), display=table,
                                     **options)
            framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT",
                                   data=gpu.types.Buffer("FLOAT", alone.size, alone))
            arrays[f"viewport_alone_{'linear' if table is None else 'srgb'}"] = np.flipud(alone)
    offscreen.free()
    arrays.update(viewport_solid=np.flipud(solid), viewport_window_depth=np.flipud(window),
                  viewport_composite=np.flipud(composite), viewport_projection=projection,
                  viewport_view=view, viewport_matrix_world=np.array(vol.matrix_world))
    api.get_vevm(vol).save(Path(out).with_suffix(".vevm"))


def viewport_handler(vol, arrays):
    """The draw handler's drawing (``gpu_viewport.draw_view``; headless Blender never calls
    the handler) with the Render settings, the scene camera's view over an empty offscreen:
    first seen, the view turned, unchanged after a rest, then far away. Saves
    ``handler_alpha`` (each draw's alpha), ``handler_trace`` (each draw's step and pixel,
    whether a rest timer is set after it and the level shown) and ``handler_level_text``
    (the sidebar's)."""
    from mathutils import Euler, Matrix
    from volumeevm.blender import gpu_viewport
    from volumeevm.blender.camera import camera_from_blender
    from volumeevm.blender.transfer import ensure_ramp

    scene = bpy.context.scene
    settings = scene.volumeevm_render
    ensure_ramp(settings)
    settings.value_lo, settings.value_hi = 2.0, 5.5  # the skull's bone
    settings.viewport = True
    camera = camera_from_blender(scene)
    h, w = camera.shape
    projection = Matrix(camera.matrix_projection().tolist())
    view = scene.camera.matrix_world.inverted()
    steps = []
    draw_volume = gpu_viewport.draw_volume

    def traced(*args, **options):
        steps.append((options["step_mm"], options.get("pixel", 1)))
        return draw_volume(*args, **options)

    gpu_viewport.draw_volume = traced
    offscreen = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
    alphas, trace = [], []
    try:
        with offscreen.bind():
            framebuffer = gpu.state.active_framebuffer_get()
            turned = Euler((0.0, 0.02, 0.0)).to_matrix().to_4x4() @ view
            far = Matrix.Translation((0.0, 0.0, -3.0)) @ turned  # level Auto: a coarser one
            for view, rest in ((view, 0.0), (turned, 0.0), (turned, gpu_viewport.REST_SECONDS),
                               (far, 0.0)):
                time.sleep(rest)
                framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
                gpu_viewport.draw_view(scene, [vol], "test", (w, h), projection, view)
                rgba = np.empty((h, w, 4), np.float32)
                framebuffer.read_color(0, 0, w, h, 4, 0, "FLOAT",
                                       data=gpu.types.Buffer("FLOAT", rgba.size, rgba))
                alphas.append(rgba[..., 3])
                trace.append((*steps[-1],
                              bpy.app.timers.is_registered(gpu_viewport._redraw_rested),
                              gpu_viewport._levels.get(vol.name, 0)))
        arrays["handler_level_text"] = np.array(gpu_viewport.shown_level(vol))
    finally:
        gpu_viewport.draw_volume = draw_volume
        offscreen.free()
        settings.viewport = False
    arrays["handler_alpha"], arrays["handler_trace"] = np.array(alphas), np.array(trace)


VIEW_TRANSFORMS = {"standard": ("Standard", 0.0, 1.0), "filmic": ("Filmic", 0.0, 1.0),
                   "agx": ("AgX", 0.0, 1.0), "agx_exposed": ("AgX", 0.7, 1.3)}
"""The colour management cases of :func:`display_colours`: view transform, exposure, gamma."""


def display_colours(arrays, meta, data_dir):
    """The CT head rendered by Render VolumeEVM's job (GPU method, transparent film) and saved
    as F12 saves it (an 8-bit PNG through the scene's colour management), and drawn by the
    viewport's handler drawing into an 8-bit sRGB texture as the viewport's overlay is, under
    each of :data:`VIEW_TRANSFORMS`: saves ``display_<case>_png`` and ``display_<case>_overlay``
    (the raw bytes, bottom row first flipped to top first) and the seconds each bake took;
    then the same with a bake that fails (an unwritable temporary folder):
    ``display_fallback_overlay`` and the sidebar's text."""
    import tempfile

    from mathutils import Matrix
    from volumeevm.blender import api, display_lut, gpu_viewport, images
    from volumeevm.blender.camera import camera_from_blender
    from volumeevm.blender.dvr import settings_options

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    vol = api.import_volume(data_dir / "ct_head_invesalius.npy")
    api.build(vol, -300.0)  # skin and bone
    api.frame_volume(vol, "FRONT").data.lens *= 2.2  # the head, not the grid's corners
    scene.render.resolution_x = scene.render.resolution_y = 128
    scene.render.resolution_percentage = 100
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 1
    scene.render.film_transparent = True
    settings = scene.volumeevm_render
    api.load_preset(settings, "ct_skin", vol)
    settings.resolution, settings.shading = "full", True
    tf = api.transfer_function(settings)
    result = api.render_dvr(vol, tf, method="gpu", options=settings_options(settings, vol, "gpu"))
    settings.viewport = True
    camera = camera_from_blender(scene)
    h, w = camera.shape
    projection = Matrix(camera.matrix_projection().tolist())
    view = Matrix(np.linalg.inv(camera.matrix_world).tolist())

    def overlay(name):
        """The handler's drawing into an 8-bit sRGB colour texture and a depth texture."""
        colour = gpu.types.GPUTexture((w, h), format="SRGB8_A8")
        depth = gpu.types.GPUTexture((w, h), format="DEPTH32F_STENCIL8")
        framebuffer = gpu.types.GPUFrameBuffer(depth_slot=depth, color_slots=colour)
        with framebuffer.bind():
            framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
            gpu_viewport.draw_view(scene, [vol], name, (w, h), projection, view)
        raw = np.array(colour.read().to_list(), np.uint8).reshape(h, w, 4)
        arrays[f"display_{name}_overlay"] = np.flipud(raw)

    meta["display_bake_seconds"] = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, (transform, exposure, gamma) in VIEW_TRANSFORMS.items():
            view_settings = scene.view_settings
            view_settings.view_transform, view_settings.look = transform, "None"
            view_settings.exposure, view_settings.gamma = exposure, gamma
            png = Path(folder) / f"{name}.png"
            images.write_png(result.dvr_image, png, scene)
            saved = bpy.data.images.load(str(png))
            saved.colorspace_settings.name = "Non-Color"
            pixels = np.empty(len(saved.pixels), np.float32)
            saved.pixels.foreach_get(pixels)
            arrays[f"display_{name}_png"] = np.flipud(pixels.reshape(h, w, 4))
            bpy.data.images.remove(saved)
            start = time.perf_counter()
            meta[f"display_{name}_current_before"] = display_lut.table(scene)[1]
            display_lut.refresh(scene)  # the timer's bake (headless: no timers run)
            meta["display_bake_seconds"][name] = time.perf_counter() - start
            overlay(name)
    display_lut.free()
    scene.view_settings.view_transform = "AgX"
    writable = tempfile.tempdir
    tempfile.tempdir = str(Path(writable or tempfile.gettempdir()) / "no such folder")
    try:
        meta["display_refreshed_without_tmp"] = display_lut.refresh(scene)
        overlay("fallback")
    finally:
        tempfile.tempdir = writable
    meta["display_colour_problem"] = gpu_viewport.colour_problem(scene)
    settings.viewport = False
    gpu_viewport._forget()


def main(out, data_dir):
    ext = load_extension()
    from volumeevm.blender import gpu_context, gpu_draw, gpu_textures

    meta = {"context": True, "reason": "", "bpy": bpy.app.version_string, "errors": {},
            "times": {}}
    arrays = {}
    try:
        gpu_context.ensure_context()
    except gpu_context.GPUUnavailable as error:
        meta.update(context=False, reason=str(error))
    if meta["context"]:
        meta["gpu"] = f"{gpu.platform.renderer_get()} ({gpu.platform.backend_type_get()})"
        for name in gpu_cases.CASES:
            try:
                vevm, cam, tf, options = gpu_cases.case(name, data_dir)
                start = time.perf_counter()
                rgba, depth, _ = gpu_draw.render_gpu(vevm, cam, tf, **options)
                meta["times"][name] = time.perf_counter() - start
                arrays[f"{name}_rgba"], arrays[f"{name}_depth"] = rgba, depth
            except Exception:  # noqa: BLE001 (reported to the test of this case)
                meta["errors"][name] = traceback.format_exc()
        meta["moving"] = moving(gpu_draw, arrays, data_dir)
        meta["state_restored"] = state_restored(gpu_draw, data_dir)
        try:  # larger than llvmpipe's 3D textures (2048)
            gpu_textures.texture_3d(np.zeros((1, 1, 16385, 2), np.float32), "RG32F")
            meta["too_large"] = ""
        except gpu_textures.VolumeEVMError as error:
            meta["too_large"] = str(error)
        try:
            vevm, cam, tf, options = gpu_cases.long_box()
            arrays["long_box_rgba"], _, meta["long_box_level"] = gpu_draw.render_gpu(
                vevm, cam, tf, **options)
        except Exception:  # noqa: BLE001 (reported to its test)
            meta["errors"]["long_box"] = traceback.format_exc()
        importlib.import_module(f"{ext.__name__}.blender.api")
        ext.register()
        from volumeevm.blender import gpu_viewport

        handlers = {"registered": gpu_viewport._drawing.handle is not None}
        try:
            meta["scene_notes"] = scene_renders(ext, arrays, out)
            handlers["textures kept"] = len(gpu_textures._volumes) > 0
            bpy.ops.wm.read_factory_settings(use_empty=True)  # a file load
            handlers["freed on load"] = len(gpu_textures._volumes) == 0
        except Exception:  # noqa: BLE001 (reported to the tests of the render job)
            meta["errors"]["scene"] = traceback.format_exc()
        try:
            display_colours(arrays, meta, data_dir)
        except Exception:  # noqa: BLE001 (reported to the tests of the viewport's colours)
            meta["errors"]["display"] = traceback.format_exc()
        finally:
            ext.unregister()
        handlers["removed"] = (gpu_viewport._drawing.handle is None and gpu_draw._shader is None
                              and len(gpu_textures._tables) == 0)
        meta["viewport_handlers"] = handlers
    np.savez(out, meta=np.array(json.dumps(meta)), **arrays)


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]))
