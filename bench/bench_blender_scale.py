"""Issue 18's walk in the real ``bpy`` on a store larger than the memory allowed: import an
OME-Zarr store, build the bone at its full level chunk by chunk, mesh it, cut it with a mesh
tool and render it, under ``VOLUMEEVM_MEMORY_LIMIT`` (6G by default).

The store is ``bench_scale.py``'s: the CT head (int16 HU) resampled by nearest neighbour to N³
and written chunk by chunk (128³ chunks, blosc-zstd; ``--store`` reuses one, else it is made
in ``--dir``, N = ``--size``, 2048 by default: 16 GiB of voxels). One Blender session runs
the script API (``blender.api``) as a user's script would:

1. ``import_volume(store)``: metadata and the coarsest level (for the histogram);
2. ``build(vol, 300)`` at level 0: the chunked build, progress lines per chunk;
3. ``make_mesh(vol)``: the exact surface as a Blender mesh;
4. ``add_tool(vol, sphere, "cut")``: a UV sphere through the skull, evaluated at once;
5. ``render_dvr`` of the cut volume, 512² from the front (``frame_volume``), ray casting at
   ``level="auto"`` (the Render setting's default), then at ``level="full"``.

Per step: wall time, the process's peak RSS so far (``VmHWM``: the Blender session included)
and what the step made. A step that fails (a refused budget) is recorded with its message
and ends the walk. The environment's ``VOLUMEEVM_MEMORY_LIMIT`` is set before the extension
loads. Kernels compile on their first use after a change (seconds each, cached on disk): run
the bench once on a small store (``--size 256``) first. Times depend on the shared machine:
read them as indications.

Usage: ``.venv/py313/bin/python bench/bench_blender_scale.py [--store S | --size N --dir D]
[--cap 6G] [--out bench/results]`` (writes ``blender_scale.json``).
"""

import argparse
import importlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

THRESHOLD_HU = 300.0
PIXELS = 512


def peak_rss():
    """The process's high-water resident size (bytes)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return None


def walk(api, core, store, steps):
    """The five steps on ``store``; appends each one's record to ``steps``."""
    import bpy

    def step(name, action):
        start = time.perf_counter()
        facts = action()
        steps.append({"step": name, "seconds": round(time.perf_counter() - start, 2),
                      "peak_rss_bytes": peak_rss(), **(facts or {})})
        print(f"[bench] {name}: {steps[-1]['seconds']} s, peak "
              f"{steps[-1]['peak_rss_bytes'] / 2 ** 30:.2f} GiB {facts or ''}", flush=True)

    vol = None

    def import_store():
        nonlocal vol
        vol = api.import_volume(str(store))
        return {"level": vol.volumeevm.level,
                "levels": len(json.loads(vol.volumeevm.zarr_levels))}

    def build():
        vevm = api.build(vol, THRESHOLD_HU)
        return {"shape": list(vevm.shape), "voxels": int(vevm.voxel_count)}

    def mesh():
        surface = api.make_mesh(vol)
        return {"polygons": len(surface.data.polygons)}

    def cut():
        vevm = api.get_vevm(vol)
        size = core.model.BLENDER_UNITS_PER_MM * min(
            n * s for n, s in zip(vevm.shape, vevm.spacing))
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.2 * size, segments=32, ring_count=16,
                                             location=_centre(vol) + _offset(0.0, -0.4 * size))
        sphere = bpy.context.active_object
        bpy.context.view_layer.update()
        api.add_tool(vol, sphere, "cut")
        state = api.stack_state(vol)
        if state.problem:
            raise RuntimeError(state.problem)
        return {"voxels": int(state.result.voxel_count)}

    def render(level):
        scene = bpy.context.scene
        scene.render.resolution_x = scene.render.resolution_y = PIXELS
        scene.render.resolution_percentage = 100
        scene.render.engine = "BLENDER_WORKBENCH"  # the scene pass: only the depth matters here
        result = api.render_dvr(vol, core.TransferFunction.preset("ct_bone"),
                                options={"level": level}, image_name=f"dvr_{level}")
        return {"visible": bool(result.visible),
                "covered_pixels": int((result.dvr_rgba[..., 3] > 0).sum())}

    step("import", import_store)
    step("build", build)
    step("mesh", mesh)
    step("cut", cut)
    api.frame_volume(vol, "FRONT")
    step("render auto", lambda: render("auto"))
    step("render full", lambda: render("full"))


def _centre(obj):
    from mathutils import Vector

    return sum((obj.matrix_world @ Vector(c) for c in obj.bound_box), Vector()) / 8


def _offset(x, y):
    from mathutils import Vector

    return Vector((x, y, 0.0))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, help="an existing store (bench_scale's)")
    parser.add_argument("--size", type=int, default=2048, help="N of the store to make")
    parser.add_argument("--dir", type=Path, default=None, help="where a made store goes")
    parser.add_argument("--cap", default="6G", help="VOLUMEEVM_MEMORY_LIMIT")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    args = parser.parse_args()
    os.environ["VOLUMEEVM_MEMORY_LIMIT"] = args.cap

    import bpy

    from bench._common import run_facts, write_json
    from sample_blends.make_demo import load_extension

    results = {"facts": {**run_facts(), "bpy": bpy.app.version_string},
               "memory_limit": args.cap, "threshold_hu": THRESHOLD_HU, "steps": []}
    with tempfile.TemporaryDirectory(dir=args.dir) as folder:
        store = args.store
        if store is None:
            from bench_scale import make_store

            store, seconds, size = make_store(Path(folder), args.size)
            results["store_write"] = {"seconds": round(seconds, 1), "bytes_on_disk": size}
        results["store"] = str(store)
        ext = load_extension()
        api = importlib.import_module(f"{ext.__name__}.blender.api")
        ext.register()
        bpy.ops.wm.read_factory_settings(use_empty=True)
        results["rss_after_start_bytes"] = peak_rss()
        try:
            walk(api, ext.volumeevm_addon, store, results["steps"])
        except Exception as error:  # recorded: a refused budget is a result
            results["failed"] = f"{type(error).__name__}: {error}"
            print(f"[bench] FAILED {results['failed']}", flush=True)
        ext.unregister()
    write_json(args.out / "blender_scale.json", results)


if __name__ == "__main__":
    main()
