"""Benchmark of a live CAD drag step in the real ``bpy`` (issue 11: one step <= 50 ms).

The CT head of ../shared/data (or its crop with ``--crop``, the one the Blender tests use) is
imported, built at 300 HU and meshed through the script API (``blender.api``); a 3-tool stack
of real mesh objects is added: a box mesh that keeps the skull's upper part, a UV sphere that
cuts through the skull and a cylinder added as material. Then one tool at a time is dragged in
small steps (``--steps`` moves of ``--step-mm``, back and forth): each step moves the object and
calls ``view_layer.update()``, so the depsgraph handler refreshes the stack exactly as when the
user drags the tool in the viewport. A step is timed as a whole (``step_s``: the depsgraph update
with the refresh inside it) and by the parts the refresh records (``stack_state(vol).timing``):
reading the tools, voxelizing the moved one, re-evaluating the stack, the core's mesh and
writing the Blender mesh. Each surface mesh is checked against the core's for the same stack.

Each configuration is run on 1 and on 2 kernel threads (``set_kernel_threads``), cold (the first
step after the stack was built) and warm (the median and best of the following steps); each
step's process CPU time is recorded beside its wall time (all threads: on a busy machine the
wall time also holds the waits for a core). Kernels the first step loads for the first time in
the session are listed (``first_use``): from the disk cache that costs milliseconds, compiling
(once per machine and version, or after an edit of a kernel's module) seconds. Run the bench
twice after changing a kernel to see the cold step of a session with a warm disk cache.

Usage (in either venv; bpy is the real wheel)::

    .venv/py313/bin/python bench/bench_cad.py --out /tmp/cad      # full CT head
    .venv/py311/bin/python bench/bench_cad.py --crop --steps 10

Prints a table and writes ``bench_cad.json`` to ``--out``.
"""

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bpy  # noqa: E402

from bench._common import run_facts, write_json  # noqa: E402
from sample_blends.make_demo import load_extension  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CROP = (slice(64, 192), slice(48, 176), slice(30, 80))  # the Blender tests' crop
THRESHOLD_HU = 300.0
PARTS = ("read_s", "voxelize_s", "evaluate_s", "mesh_s", "write_s")
FIRST_USE = []  # kernels loaded or compiled for the first time in this session


def write_volume(folder, crop):
    """The CT head (or its crop) as ``.npy`` with the JSON sidecar the reader takes."""
    meta = json.loads((DATA / "ct_head_invesalius.json").read_text())
    array = np.load(DATA / "ct_head_invesalius.npy")
    if crop:
        array = np.ascontiguousarray(array[CROP])
    path = Path(folder) / ("ct_crop.npy" if crop else "ct_head.npy")
    np.save(path, array)
    side = {k: meta[k] for k in ("spacing_mm", "spacing_known", "units", "axis_order", "dtype")}
    side["shape"] = list(array.shape)
    path.with_suffix(".json").write_text(json.dumps(side))
    return path


def world_at(core, vol_obj, vevm, fraction):
    """World position (Blender units) of the point at ``fraction`` (3 numbers in [0, 1]) of the
    volume's grid (voxel-centre index space)."""
    index = (np.asarray(vevm.shape) - 1) * np.asarray(fraction, float)
    to_world = np.array(vol_obj.matrix_world) @ core.grid_to_world(
        vevm.spacing, vevm.origin, vevm.orientation)
    return tuple((to_world @ np.append(index, 1.0))[:3])


def extent_bu(core, vevm):
    """The grid's size along x, y, z in Blender units."""
    return np.asarray(vevm.shape) * np.asarray(vevm.spacing) * core.model.BLENDER_UNITS_PER_MM


def add_tools(core, api, vol, vevm):
    """The 3-tool stack (real mesh objects): keep box, cut sphere, add cylinder."""
    size = extent_bu(core, vevm)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=world_at(core, vol, vevm, (0.5, 0.5, 0.62)))
    box = bpy.context.active_object
    box.name = "KeepBox"
    box.scale = tuple(size * (0.9, 0.9, 0.8))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=float(size[:2].min() * 0.09), segments=32,
                                         ring_count=16,
                                         location=world_at(core, vol, vevm, (0.5, 0.12, 0.65)))
    sphere = bpy.context.active_object
    sphere.name = "CutSphere"
    bpy.ops.mesh.primitive_cylinder_add(radius=float(size[:2].min() * 0.03),
                                        depth=float(size[2] * 0.3), vertices=32,
                                        location=world_at(core, vol, vevm, (0.3, 0.5, 0.5)))
    cylinder = bpy.context.active_object
    cylinder.name = "AddCylinder"
    bpy.context.view_layer.update()
    for tool, operation in ((box, "keep"), (sphere, "cut"), (cylinder, "add")):
        api.add_tool(vol, tool, operation)
    bpy.context.view_layer.objects.active = vol
    return {"keep": box, "cut": sphere, "add": cylinder}


def check_surface(core, surface, result):
    """The Blender surface mesh equals the core's mesh of ``result`` exactly."""
    verts_mm, polys = result.mesh()
    mesh = surface.data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    loops = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", loops)
    expected = (np.asarray(verts_mm) * core.model.BLENDER_UNITS_PER_MM).astype(np.float32).ravel()
    if not (np.array_equal(co, expected) and np.array_equal(loops, polys.indices)):
        raise AssertionError("the surface mesh differs from the core's mesh of the stack")


def drag(api, vol, tool, steps, step_bu, run):
    """Move ``tool`` along x in ``steps`` steps; the timing of each step.

    Odd runs drag back (-x), even runs forward, each from an offset of ``run / 7`` of a step,
    so that no placement repeats an earlier one (the runtime's tool cache would find it).
    """
    direction = 1.0 if run % 2 == 0 else -1.0
    records = []
    for n in range(steps):
        state = api.stack_state(vol)
        before = state.timing
        move = direction * step_bu * (1.0 + (run / 7.0 if n == 0 else 0.0))
        FIRST_USE.clear()
        start, cpu = time.perf_counter(), time.process_time()
        tool.location.x += move
        bpy.context.view_layer.update()  # the depsgraph handler refreshes the stack
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
        timing = api.stack_state(vol).timing
        if timing is before or state.problem:
            raise AssertionError(f"step {n} did not refresh the stack: {state.problem!r}")
        if timing["voxelized"] != 1:
            raise AssertionError(f"step {n} voxelized {timing['voxelized']} tools, not 1")
        record = {"step_s": elapsed, "cpu_s": cpu, **{p: timing.get(p, 0.0) for p in PARTS},
                  "recomputed": timing["recomputed"], "polygons": timing.get("polygons", 0),
                  "first_use": list(FIRST_USE)}
        records.append(record)
    return records


def summary(records):
    """Cold (first step) and warm (median and best of the rest) per part, in ms."""
    def ms(values):
        return round(1000.0 * values, 2)

    warm = records[1:]
    keys = ("step_s", "cpu_s") + PARTS
    out = {"cold_ms": {k: ms(records[0][k]) for k in keys},
           "first_use": records[0]["first_use"]}
    out["warm_median_ms"] = {k: ms(statistics.median(r[k] for r in warm)) for k in keys}
    out["warm_best_ms"] = {k: ms(min(r[k] for r in warm)) for k in keys}
    out["recomputed"] = sorted({r["recomputed"] for r in records})
    out["polygons"] = records[-1]["polygons"]
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--crop", action="store_true", help="the tests' 128x128x50 crop")
    parser.add_argument("--steps", type=int, default=16, help="drag steps per tool and threads")
    parser.add_argument("--step-mm", type=float, default=1.0, help="length of one drag step")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--tools", nargs="+", default=["cut", "keep", "add"],
                        choices=["cut", "keep", "add"], help="which tools to drag")
    parser.add_argument("--out", type=Path, required=True, help="folder for bench_cad.json")
    args = parser.parse_args()

    ext = load_extension()
    import importlib

    api = importlib.import_module(f"{ext.__name__}.blender.api")
    core = ext.volumeevm_addon
    ext.register()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    facts = run_facts()
    facts["bpy"] = bpy.app.version_string
    results = {"facts": facts, "dataset": "ct_head crop" if args.crop else "ct_head",
               "threshold_hu": THRESHOLD_HU, "step_mm": args.step_mm, "runs": []}
    with tempfile.TemporaryDirectory() as folder:
        path = write_volume(folder, args.crop)
        vol = api.import_volume(str(path))
        start = time.perf_counter()
        vevm = api.build(vol, THRESHOLD_HU)
        api.make_mesh(vol)
        results["build_and_mesh_s"] = round(time.perf_counter() - start, 3)
        results["voxels"] = vevm.voxel_count
        start = time.perf_counter()
        tools = add_tools(core, api, vol, vevm)
        results["add_three_tools_s"] = round(time.perf_counter() - start, 3)
        check_surface(core, vol.volumeevm.surface, api.stack_state(vol).result)
        core.system.set_kernel_compile_hook(FIRST_USE.append)  # here: each job puts its own back
        step_bu = args.step_mm * core.model.BLENDER_UNITS_PER_MM
        run_number = 0
        for threads in args.threads:
            core.set_kernel_threads(threads)
            for name in args.tools:
                records = drag(api, vol, tools[name], args.steps, step_bu, run_number // 3)
                run_number += 1
                check_surface(core, vol.volumeevm.surface, api.stack_state(vol).result)
                run = {"tool": name, "entry": list(tools).index(name) + 1, "threads": threads,
                       **summary(records),
                       "steps_ms": [round(1000 * r["step_s"], 1) for r in records]}
                results["runs"].append(run)
                print(f"{threads} thr  drag {name:4s} (entry {run['entry']})  "
                      f"cold {run['cold_ms']['step_s']:7.1f} ms  "
                      f"warm median {run['warm_median_ms']['step_s']:7.1f} ms (cpu "
                      f"{run['warm_median_ms']['cpu_s']:.1f})  best "
                      f"{run['warm_best_ms']['step_s']:7.1f} ms  | median parts: "
                      + "  ".join(f"{p[:-2]} {run['warm_median_ms'][p]:.1f}" for p in PARTS)
                      + f"  | {run['polygons']} polygons", flush=True)
        core.set_kernel_threads(None)
    ext.unregister()
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "bench_cad.json", results)


if __name__ == "__main__":
    main()
