"""The demo scene: sample skull -> VolumeEVM -> a drill (CAD tool) cuts into it -> the scene
rendered by Cycles with its depth pass -> the skull's direct volume rendering (our NumPy core,
rays stopped at the drill) laid over it.

Run with ``make demo`` (or ``python sample_blends/make_demo.py --out out`` in a venv with the bpy
wheel; or inside Blender: ``blender --background --python sample_blends/make_demo.py -- --out
out``). Writes ``OUT/demo.png`` and ``OUT/demo.exr`` (R, G, B, A, Z), ``OUT/demo_mesh.png`` (the
EVM surface mesh by Cycles) and ``OUT/demo.blend`` (with its sidecar
``OUT/demo_volumeevm/ct_skull_cgal.vevm``, the DVR image packed and the compositor set up, so F12
in it gives demo.png again) and prints progress lines.
"""

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

REPO = Path(__file__).resolve().parents[1]
SAMPLE = Path(__file__).resolve().parent / "data" / "ct_skull_cgal.npy"
THRESHOLD = 2.9  # the isovalue CGAL meshes this skull at
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


def bone_material():
    material = bpy.data.materials.new("Bone")
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True  # always on (and deprecated) from 5.0
    bsdf = material.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.89, 0.85, 0.76, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.55
    return material


def metal_material():
    material = bpy.data.materials.new("Drill Steel")
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True
    bsdf = material.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.55, 0.58, 0.62, 1.0)
    bsdf.inputs["Metallic"].default_value = 1.0
    bsdf.inputs["Roughness"].default_value = 0.3
    return material


def drill(scene, tip, direction, *, radius=0.01, length=0.16, segments=32):
    """A closed cylinder mesh object ("Drill") from ``tip`` along ``direction`` (Blender units)."""
    angles = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])
    co = np.vstack([np.column_stack([ring, np.zeros(segments)]),
                    np.column_stack([ring, np.full(segments, length)])])
    sides = [(i, (i + 1) % segments, segments + (i + 1) % segments, segments + i)
             for i in range(segments)]
    caps = [tuple(range(segments - 1, -1, -1)), tuple(range(segments, 2 * segments))]
    mesh = bpy.data.meshes.new("Drill")
    mesh.from_pydata(co.tolist(), [], sides + caps)
    mesh.update()
    obj = bpy.data.objects.new("Drill", mesh)
    obj.location = tip
    obj.rotation_euler = Vector(direction).to_track_quat("Z", "Y").to_euler()
    mesh.materials.append(metal_material())
    scene.collection.objects.link(obj)
    return obj


def skull_transfer_function():
    """Bone-like classification in the skull's own density units (0 .. 5.4, region >= 2.9):
    transparent at the isovalue (so the region's voxel faces do not show) and ivory, denser
    towards the top of the range; opacity per mm (voxels are about 3.9 mm)."""
    from volumeevm.volumeevm_addon import TransferFunction

    return TransferFunction([
        (2.9, 0.80, 0.62, 0.50, 0.00),
        (3.4, 0.85, 0.68, 0.55, 0.03),
        (4.2, 0.93, 0.85, 0.72, 0.08),
        (5.43, 1.00, 0.98, 0.92, 0.30),
    ], name="skull bone")


def look_at(obj, target):
    direction = Vector(target) - obj.location
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def stage(scene, surface, size):
    """Camera, lights and world framing the surface (bounding box from its vertices)."""
    co = np.empty(len(surface.data.vertices) * 3, np.float32)
    surface.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(axis=0), co.max(axis=0)
    centre = Vector(((lo + hi) / 2).tolist())
    radius = float(np.linalg.norm(hi - lo)) / 2

    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.lens = 50
    camera.data.clip_start = radius / 100
    camera.data.clip_end = radius * 20
    # LPS: the face looks along -Y (anterior), +Z is up: a front-left view from slightly above.
    camera.location = centre + Vector((-0.2, -1.0, 0.1)).normalized() * radius * 3.6
    look_at(camera, centre)
    scene.collection.objects.link(camera)
    scene.camera = camera

    key = bpy.data.objects.new("Key", bpy.data.lights.new("Key", "AREA"))
    key.data.energy = 6.0 * radius ** 2 / 0.02
    key.data.size = 3 * radius
    key.location = centre + Vector((-1.0, -1.2, 1.2)) * radius * 2.5
    look_at(key, centre)
    scene.collection.objects.link(key)
    fill = bpy.data.objects.new("Fill", bpy.data.lights.new("Fill", "SUN"))
    fill.data.energy = 0.8
    fill.rotation_euler = (0.9, 0.0, -2.4)
    scene.collection.objects.link(fill)

    world = bpy.data.worlds.new("World")
    scene.world = world
    if bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.05, 0.06, 0.08, 1)

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 32
    scene.cycles.use_denoising = False
    render.resolution_x = render.resolution_y = size
    render.resolution_percentage = 100
    render.image_settings.file_format = "PNG"
    render.film_transparent = False


def render_png(scene, path):
    """Render to ``path`` atomically (a temporary file in the same folder, then a rename)."""

    from volumeevm.volumeevm_addon import write_atomically

    def render(temporary):
        scene.render.filepath = str(temporary)
        bpy.ops.render.render(write_still=True)

    write_atomically(path, render, overwrite=True)


def main(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out", help="output folder (made if missing)")
    parser.add_argument("--size", type=int, default=480, help="render size in pixels")
    args = parser.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    say(f"Blender {bpy.app.version_string}, NumPy {np.__version__}")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ext = load_extension()
    ext.register()
    try:
        from volumeevm.blender import api  # the script API, as a script imports it

        scene = bpy.context.scene
        say(f"importing {SAMPLE.name}")
        volume = api.import_volume(SAMPLE)
        s = volume.volumeevm
        say(f"volume {tuple(s.shape)} voxels, spacing {tuple(round(v, 3) for v in s.spacing)} mm, "
            f"values {s.value_min:.3g} .. {s.value_max:.3g}")
        say(f"building the VolumeEVM at {THRESHOLD}")
        vevm = api.build(volume, THRESHOLD)
        report = vevm.size_report()
        say(f"{vevm.voxel_count} voxels, {len(vevm.evm)} extreme vertices, "
            f"{report['total_bytes']} bytes = {100 * report['ratio']:.1f}% of the dense array")
        surface = api.make_mesh(volume)
        surface.data.materials.append(bone_material())
        say(f"mesh {surface.name}: {len(surface.data.vertices)} vertices, "
            f"{len(surface.data.polygons)} polygons")
        stage(scene, surface, args.size)
        # The CAD tool: a drill entering the left side of the forehead, cutting its hole.
        tool = drill(scene, tip=(0.105, 0.085, 0.165), direction=(-0.45, -1.0, 0.35))
        say("cutting the skull with the drill (tool stack)")
        result = api.add_tool(volume, tool, "cut")
        say(f"after the cut: {result.voxel_count} voxels")
        say(f"rendering the mesh {args.size}x{args.size} with Cycles "
            f"(CPU, {scene.cycles.samples} samples)")
        render_png(scene, out / "demo_mesh.png")
        say(f"wrote {out / 'demo_mesh.png'}")
        # The volume render: scene (drill, lights, world) by Cycles with depth, the skull's DVR
        # from the scene camera stopped at that depth, alpha over; the surface stays hidden.
        surface.hide_render = True
        settings = scene.volumeevm_render
        settings.volume = volume
        api.set_transfer_function(settings, skull_transfer_function())
        settings.method = "raycast"
        settings.mode = "over"
        settings.shading = True
        settings.quality = 2.0  # two samples per voxel along rays: no banding at this zoom
        settings.use_exr, settings.exr_path = True, str(out / "demo.exr")
        settings.use_png, settings.png_path = True, str(out / "demo.png")
        settings.overwrite = True  # the demo's own outputs
        say(f"rendering the scene and the skull's DVR ({settings.method}, {settings.mode})")
        dvr_start = time.perf_counter()
        bpy.ops.volumeevm.render_dvr()
        say(f"wrote {out / 'demo.png'} and {out / 'demo.exr'} "
            f"({time.perf_counter() - dvr_start:.1f} s)")
        bpy.ops.volumeevm.setup_compositor()
        dvr_image = bpy.data.images[f"{settings.image_name} DVR"]
        dvr_image.pack()  # kept in the .blend: F12 there lays it over the render again
        settings.exr_path, settings.png_path = "//demo.exr", "//demo.png"
        settings.overwrite = False
        bpy.context.preferences.filepaths.save_version = 0  # no demo.blend1 backups
        bpy.ops.wm.save_as_mainfile(filepath=str(out / "demo.blend"))
        say(f"wrote {out / 'demo.blend'} and its VolumeEVM {volume.volumeevm.vevm_path}")
    finally:
        ext.unregister()
    say(f"done in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
