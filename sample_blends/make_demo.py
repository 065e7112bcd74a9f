"""The demo scene: a real CT head -> VolumeEVM of its bone -> a trephine (a CAD tool) cuts a
window into the skull -> the bone's direct volume rendering laid over the scene (drill, lights)
-> the exact capped surface by Cycles -> the region as a native Volume rendered by Cycles -> a
turntable of the composite.

Run with ``make demo`` (it fetches the scan first, see ``sample_blends/data/README.md``), or
``python sample_blends/make_demo.py --out out`` in a venv with the bpy wheel once
``sample_blends/fetch_ct_head.py sample_blends/data`` has run (inside Blender: ``blender
--background --python sample_blends/make_demo.py -- --out out``). Writes into OUT:

- ``demo.png`` and ``demo.exr`` (R, G, B, A, Z): the bone's DVR (ray cast, gradient-shaded)
  composited over the Cycles render of the scene, rays stopped at the drill's depth;
- ``demo_mesh.png``: the EVM's exact surface of the cut skull by Cycles, its cut capped;
- ``demo_cycles.png``: the same view by Cycles alone, the region as a native Volume object
  (OpenVDB grid, material from the same transfer function), at half the size;
- ``turntable/frame_0001.png`` ... and ``turntable.mp4`` (Blender's own FFmpeg, H.264): the
  camera orbiting the head, each frame rendered by :func:`render_dvr_animation`;
- ``demo.blend`` (sidecar ``demo_volumeevm/``; the DVR image packed and the compositor set up,
  so F12 in it gives demo.png again).

Progress lines ``[demo] ...`` are printed.
"""

import argparse
import importlib.util
import math
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

REPO = Path(__file__).resolve().parents[1]
SAMPLE = Path(__file__).resolve().parent / "data" / "ct_head_invesalius.npy"
THRESHOLD = 150.0  # HU: bone (the ct_bone preset is transparent below it)
PACKAGE = "volumeevm"


def say(text):
    print(f"[demo] {text}", flush=True)


def load_extension():
    """The extension package from this source tree, imported once as ``volumeevm`` (installed,
    Blender names it ``bl_ext.<repo>.volumeevm``). The Blender tests load it with this too."""
    if PACKAGE not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            PACKAGE, REPO / "__init__.py", submodule_search_locations=[str(REPO)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[PACKAGE] = module
        spec.loader.exec_module(module)
    return sys.modules[PACKAGE]


def principled(name, colour, *, metallic=0.0, roughness=0.5):
    material = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True  # always on (and deprecated) from 5.0
    bsdf = material.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    return material


def cylinder(scene, name, base, direction, *, radius, length, segments=48):
    """A closed cylinder mesh object from ``base`` along ``direction`` (Blender units)."""
    angles = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])
    co = np.vstack([np.column_stack([ring, np.zeros(segments)]),
                    np.column_stack([ring, np.full(segments, length)])])
    sides = [(i, (i + 1) % segments, segments + (i + 1) % segments, segments + i)
             for i in range(segments)]
    caps = [tuple(range(segments - 1, -1, -1)), tuple(range(segments, 2 * segments))]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(co.tolist(), [], sides + caps)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = base
    obj.rotation_euler = Vector(direction).to_track_quat("Z", "Y").to_euler()
    scene.collection.objects.link(obj)
    return obj


def look_at(obj, target):
    direction = Vector(target) - obj.location
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def bounds(volume):
    """Centre and radius (Blender units) of the volume's box in world space, from the volume
    object's own placement (its surface mesh is placed differently)."""
    from volumeevm.blender.framing import volume_corners

    corners = volume_corners(volume)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return Vector(((lo + hi) / 2).tolist()), float(np.linalg.norm(hi - lo)) / 2


def stage(scene, centre, radius, view, size):
    """Camera (on an empty at the centre that the turntable turns), lights, world, Cycles."""
    pivot = bpy.data.objects.new("Turntable", None)
    pivot.location = centre
    scene.collection.objects.link(pivot)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.lens = 60
    camera.data.clip_start = radius / 100
    camera.data.clip_end = radius * 20
    camera.parent = pivot  # placed in the pivot's frame: at the pivot's origin is the centre
    camera.location = Vector(view).normalized() * radius * 2.7
    look_at(camera, Vector())
    scene.collection.objects.link(camera)
    scene.camera = camera

    key = bpy.data.objects.new("Key", bpy.data.lights.new("Key", "AREA"))
    key.data.energy = 8.0 * radius ** 2 / 0.02
    key.data.size = 3 * radius
    key.location = centre + Vector((1.0, 1.2, 1.4)) * radius * 2.5
    look_at(key, centre)
    scene.collection.objects.link(key)
    fill = bpy.data.objects.new("Fill", bpy.data.lights.new("Fill", "SUN"))
    fill.data.energy = 1.0
    fill.rotation_euler = (0.9, 0.0, 2.4)
    scene.collection.objects.link(fill)

    world = bpy.data.worlds.new("World")
    scene.world = world
    if bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.03, 0.035, 0.045, 1)

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.use_denoising = False
    render.resolution_x = render.resolution_y = size
    render.resolution_percentage = 100
    render.image_settings.file_format = "PNG"
    render.film_transparent = False
    return pivot


def render_png(scene, path):
    """Render to ``path`` atomically (a temporary file in the same folder, then a rename)."""

    from volumeevm.volumeevm_addon.system import write_atomically

    def render(temporary):
        scene.render.filepath = str(temporary)
        bpy.ops.render.render(write_still=True)

    write_atomically(path, render, overwrite=True)


def mm(volume, point_mm):
    """A point given in the scan's millimetres (x, y, z from voxel (0, 0, 0)'s corner) in world
    coordinates (1 mm = 0.001 BU, then the volume object's matrix)."""
    return volume.matrix_world @ (Vector(point_mm) * 0.001)


def turntable(scene, pivot, frames):
    """One turn of the camera's pivot about the vertical over ``frames`` frames (linear)."""
    scene.frame_start, scene.frame_end = 1, frames
    start = pivot.rotation_euler.z
    for frame, angle in ((1, 0.0), (frames + 1, 2 * math.pi)):
        pivot.rotation_euler.z = start + angle
        pivot.keyframe_insert("rotation_euler", index=2, frame=frame)
    action = pivot.animation_data.action
    curves = action.fcurves if hasattr(action, "fcurves") else [
        curve for layer in action.layers for strip in layer.strips
        for bag in strip.channelbags for curve in bag.fcurves]
    for curve in curves:
        for point in curve.keyframe_points:
            point.interpolation = "LINEAR"


def movie(frames_pattern, frames, path, fps):
    """The PNG frames as an H.264 MP4, by Blender's own FFmpeg: an image-sequence strip in the
    sequencer of a scene of its own, rendered as an animation."""
    from volumeevm.volumeevm_addon.system import write_atomically

    first = Path(frames_pattern.replace("####", "0001"))
    scene = bpy.data.scenes.new("Turntable movie")
    editor = scene.sequence_editor_create()
    strips = editor.strips if hasattr(editor, "strips") else editor.sequences
    strip = strips.new_image("frames", str(first), channel=1, frame_start=1)
    for number in range(2, frames + 1):
        strip.elements.append(first.name.replace("0001", f"{number:04d}"))
    render = scene.render
    render.resolution_x, render.resolution_y = bpy.context.scene.render.resolution_x, \
        bpy.context.scene.render.resolution_y
    render.resolution_percentage = 100
    render.fps = fps
    scene.frame_start, scene.frame_end = 1, frames
    settings = render.image_settings
    if hasattr(settings, "media_type"):
        settings.media_type = "VIDEO"  # Blender 5
    settings.file_format = "FFMPEG"
    render.ffmpeg.format, render.ffmpeg.codec = "MPEG4", "H264"
    render.ffmpeg.constant_rate_factor = "HIGH"
    render.use_sequencer = True

    def write(temporary):
        render.filepath = str(temporary)
        bpy.ops.render.render(animation=True, scene=scene.name)
        written = Path(render.frame_path(frame=1))
        written.replace(temporary)

    write_atomically(path, write, overwrite=True)
    bpy.data.scenes.remove(scene)


def main(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out", help="output folder (made if missing)")
    parser.add_argument("--size", type=int, default=512, help="still size in pixels")
    parser.add_argument("--turntable-size", type=int, default=320, help="turntable frame size")
    parser.add_argument("--frames", type=int, default=24, help="turntable frames")
    parser.add_argument("--scan", type=Path, default=SAMPLE,
                        help="the CT head (.npy beside its .json; default: the fetched one)")
    args = parser.parse_args(argv)
    out = Path(args.out).resolve()
    (out / "turntable").mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    say(f"Blender {bpy.app.version_string}, NumPy {np.__version__}")
    if not args.scan.exists():
        sys.exit(f"[demo] {args.scan} is missing: run `python sample_blends/fetch_ct_head.py "
                 f"{SAMPLE.parent}` (make demo does)")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ext = load_extension()
    ext.register()
    try:
        from volumeevm.blender import api  # the script API, as a script imports it
        from volumeevm.volumeevm_addon import Shading, TransferFunction

        scene = bpy.context.scene
        say(f"importing {args.scan.name}")
        volume = api.import_volume(args.scan)
        s = volume.volumeevm
        say(f"volume {tuple(s.shape)} voxels, spacing {tuple(round(v, 3) for v in s.spacing)} mm, "
            f"values {s.value_min:.0f} .. {s.value_max:.0f} HU")
        say(f"building the VolumeEVM of the bone (>= {THRESHOLD:.0f} HU)")
        step = time.perf_counter()
        vevm = api.build(volume, THRESHOLD)
        report = vevm.size_report()
        say(f"{vevm.voxel_count} voxels, {len(vevm.evm)} extreme vertices, "
            f"{report['total_bytes'] / 1e6:.1f} MB = {100 * report['ratio']:.1f}% of the dense "
            f"array ({time.perf_counter() - step:.1f} s)")

        # The CAD tool: a trephine cuts a round window into the left parietal bone; the stack is
        # applied and the trephine withdrawn along its axis, so the camera sees into the window.
        step = time.perf_counter()
        centre_mm = Vector((124.0, 110.0, 95.0))  # inside the cranium
        axis = Vector((-1.0, 0.55, 0.85)).normalized()
        radius_mm, depth_mm = 21.0, 70.0
        trephine = cylinder(scene, "Trephine", mm(volume, centre_mm + axis * 40.0),
                            (volume.matrix_world.to_3x3() @ axis), radius=radius_mm * 1e-3,
                            length=depth_mm * 1e-3)
        result = api.add_tool(volume, trephine, "cut")
        api.apply_stack(volume)
        # Withdrawn along its axis and set aside (the axis is close to the camera's line of
        # sight), so the camera sees into the window with the trephine beside it.
        aside = axis.cross(Vector((-1.0, 0.7, 0.8))).normalized()
        trephine.location += volume.matrix_world.to_3x3() @ (axis * 0.04 - aside * 0.1)
        say(f"window cut: {result.voxel_count} voxels "
            f"({time.perf_counter() - step:.1f} s)")
        trephine.data.materials.append(principled("Steel", (0.62, 0.64, 0.68), metallic=1.0,
                                                  roughness=0.25))

        surface = api.make_mesh(volume)
        surface.data.materials.append(principled("Bone", (0.89, 0.85, 0.76), roughness=0.55))
        say(f"exact surface {surface.name}: {len(surface.data.vertices)} vertices, "
            f"{len(surface.data.polygons)} polygons (the window's cut capped)")
        bpy.context.view_layer.update()
        centre, radius = bounds(volume)
        view = volume.matrix_world.to_3x3() @ Vector((-1.0, 0.7, 0.8))
        pivot = stage(scene, centre, radius, view, args.size)

        scene.cycles.samples = 64
        say(f"rendering the exact surface {args.size}x{args.size} with Cycles "
            f"(CPU, {scene.cycles.samples} samples)")
        step = time.perf_counter()
        render_png(scene, out / "demo_mesh.png")
        say(f"wrote {out / 'demo_mesh.png'} ({time.perf_counter() - step:.1f} s)")

        # The volume render: the scene (trephine, lights, world) by Cycles with depth, the bone's
        # DVR from the scene camera stopped at that depth, alpha over; the surface stays hidden.
        tf = TransferFunction.preset("ct_bone")
        options = {"shading": Shading(), "step_mm": 0.8}
        scene.cycles.samples = 16
        say(f"rendering the scene and the bone's DVR {args.size}x{args.size} (ray cast, shaded)")
        step = time.perf_counter()
        result = api.render_dvr(volume, tf, method="raycast", options=options,
                                exr_path=str(out / "demo.exr"), png_path=str(out / "demo.png"),
                                overwrite=True)
        say(f"wrote {out / 'demo.png'} and {out / 'demo.exr'} ({time.perf_counter() - step:.1f} s)")

        # The same scene rendered by Cycles alone, through the native Volume: the region as an
        # OpenVDB grid with a material from the same transfer function (emission and absorption,
        # the optical model of our DVR), so Cycles' picture agrees with ours.
        settings = scene.volumeevm_render
        settings.volume = volume
        api.set_transfer_function(settings, tf)
        say("writing the region as a native Volume object (OpenVDB)")
        step = time.perf_counter()
        native = api.make_volume_object(volume)
        say(f"{native.name}: {time.perf_counter() - step:.1f} s")
        surface.hide_render = True
        scene.cycles.samples = 32
        half = args.size // 2
        scene.render.resolution_x = scene.render.resolution_y = half
        say(f"rendering the native Volume {half}x{half} with Cycles ({scene.cycles.samples} "
            f"samples)")
        step = time.perf_counter()
        render_png(scene, out / "demo_cycles.png")
        say(f"wrote {out / 'demo_cycles.png'} ({time.perf_counter() - step:.1f} s)")
        native.hide_render = True  # the turntable and F12 in demo.blend show our DVR

        size = args.turntable_size
        scene.render.resolution_x = scene.render.resolution_y = size
        scene.cycles.samples = 8
        turntable(scene, pivot, args.frames)
        pattern = str(out / "turntable" / "frame_####.png")
        say(f"turntable: {args.frames} frames {size}x{size} (scene by Cycles, DVR ray cast)")
        step = time.perf_counter()
        api.render_dvr_animation(volume, tf, png_path=pattern, overwrite=True,
                                 method="raycast", options=options)
        say(f"wrote {args.frames} frames ({time.perf_counter() - step:.1f} s)")
        movie(pattern, args.frames, out / "turntable.mp4", fps=12)
        say(f"wrote {out / 'turntable.mp4'}")

        scene.render.resolution_x = scene.render.resolution_y = args.size
        scene.frame_set(1)
        settings.shading = True
        api.setup_compositor(scene, result.dvr_image)
        result.dvr_image.pack()  # kept in the .blend: F12 there lays it over the render again
        bpy.context.preferences.filepaths.save_version = 0  # no demo.blend1 backups
        bpy.ops.wm.save_as_mainfile(filepath=str(out / "demo.blend"))
        say(f"wrote {out / 'demo.blend'} and its VolumeEVM {volume.volumeevm.vevm_path}")
    finally:
        ext.unregister()
    say(f"done in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
