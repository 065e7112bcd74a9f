"""Benchmark of the EVM core against its peers, side by side in one run (issues 2 and 11).

On the CT head of ../shared/data at a skin and a bone threshold (``rows``), and on two MRIs
(``mri_rows``, surface only):

- EVM extraction + closed mesh (from the thresholded array) against scikit-image
  ``marching_cubes`` and VTK's flying edges (``vtkFlyingEdges3D``) on the same threshold, on one
  thread and on all (``kernel_threads``; VTK's STDThread backend; marching cubes has one);
- mesh polygons against unit boundary faces;
- EVM Boolean (section sweep) against a dense NumPy Boolean + re-extraction, cutting by a box
  and by a sphere (CT head);
- VolumeEVM bytes against the dense array (CT head);
- the compiled kernels' first use (``kernels``): a fresh process meshing the CT bone with an
  empty kernel cache (compiling) and again with it filled (loading), against the warm call.

Each timing is the best of ``--repeat`` runs of the call alone (inputs built beforehand, kernels
compiled by a first call). Prints a table and writes JSON (with versions and commit) to
``--out``.

Usage: ``python bench/bench_evm.py --out bench/results``
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._common import best_time, run_facts, write_json  # noqa: E402
from volumeevm_addon import EVM, VolumeEVM, kernel_threads, set_kernel_threads  # noqa: E402

DATA = REPO.parent / "shared" / "data"
TARGETS = {"extract_mesh_speedup_vs_marching_cubes": 3.0,
           "extract_mesh_speedup_vs_vtk_flying_edges": 1.0,
           "mesh_faces_per_unit_face_bone": 0.4, "bytes_vs_dense_bone": 0.35}
MRIS = [("mr_brainsmall_volpack", 60.0), ("mr_t1_itk_kmeans", 50.0)]
FIRST_USE = """
import json, sys, time
start = time.perf_counter()
sys.path.insert(0, sys.argv[1])
import numpy as np
import volumeevm_addon
volumeevm_addon.system.set_kernel_cache_dir(sys.argv[2])
mask = np.load(sys.argv[3]) >= 300
ready = time.perf_counter()
volumeevm_addon.EVM.from_mask(mask).mesh()
print(json.dumps({"import_s": ready - start, "first_call_s": time.perf_counter() - ready}))
"""


def unit_faces(mask):
    padded = np.pad(mask, 1).astype(np.int8)
    return sum(int(np.count_nonzero(np.diff(padded, axis=axis))) for axis in range(3))


def load(name):
    meta = json.loads((DATA / f"{name}.json").read_text())
    return np.load(DATA / f"{name}.npy"), tuple(meta["spacing_mm"])


def flying_edges(array, spacing):
    """A function running VTK's flying edges on ``array`` at a threshold, on some threads."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    image = vtk.vtkImageData()
    image.SetDimensions(*array.shape)
    image.SetSpacing(*spacing)
    image.GetPointData().SetScalars(numpy_to_vtk(array.astype(np.float32).ravel(order="F"), deep=1))
    vtk.vtkSMPTools.SetBackend("STDThread")

    def run(threshold, threads):
        vtk.vtkSMPTools.Initialize(threads)
        surface = vtk.vtkFlyingEdges3D()
        surface.SetInputData(image)
        surface.SetValue(0, threshold)
        surface.ComputeNormalsOff()
        surface.ComputeGradientsOff()
        surface.ComputeScalarsOff()
        surface.Update()
        return surface.GetOutput().GetNumberOfCells()

    return run


def surface_row(array, spacing, threshold, repeat):
    """EVM extraction + mesh against marching cubes and flying edges at ``threshold``."""
    from skimage.measure import marching_cubes

    mask = array >= threshold
    as_float = array.astype(np.float32)
    vtk_run = flying_edges(array, spacing)
    threads = kernel_threads()
    evm = EVM.from_mask(mask)
    evm.mesh()  # compiles the kernels (or loads them): the timings below are warm
    row = {"threshold_hu": threshold, "voxels": int(np.count_nonzero(mask)),
           "extreme_vertices": len(evm), "threads": threads}
    for label, count in (("_1thread", 1), ("", threads)):
        previous = set_kernel_threads(count)
        try:
            row[f"evm_extract_mesh{label}_s"], (_, polygons) = best_time(
                lambda: EVM.from_mask(array >= threshold).mesh(), repeat)
        finally:
            set_kernel_threads(previous)
        row[f"vtk_flying_edges{label}_s"], vtk_triangles = best_time(
            lambda: vtk_run(threshold, count), repeat)
    row["marching_cubes_s"], (_, mc_faces, _, _) = best_time(
        lambda: marching_cubes(as_float, level=threshold, spacing=spacing), repeat)
    row.update({
        "extract_mesh_speedup_vs_marching_cubes":
            row["marching_cubes_s"] / row["evm_extract_mesh_s"],
        "extract_mesh_speedup_vs_vtk_flying_edges":
            row["vtk_flying_edges_s"] / row["evm_extract_mesh_s"],
        "extract_mesh_1thread_speedup_vs_vtk_flying_edges_1thread":
            row["vtk_flying_edges_1thread_s"] / row["evm_extract_mesh_1thread_s"],
        "mesh_polygons": len(polygons),
        "marching_cubes_triangles": len(mc_faces),
        "vtk_flying_edges_triangles": vtk_triangles,
        "unit_faces": unit_faces(mask),
    })
    row["mesh_faces_per_unit_face"] = row["mesh_polygons"] / row["unit_faces"]
    return row


def first_use(warm_s):
    """The kernels' first use in a fresh process: compiling (empty cache), then loading."""
    with tempfile.TemporaryDirectory() as cache:
        command = [sys.executable, "-c", FIRST_USE, str(REPO), cache,
                   str(DATA / "ct_head_invesalius.npy")]
        cold, warm = (json.loads(subprocess.run(command, check=True, capture_output=True, text=True,
                                                env=dict(os.environ)).stdout) for _ in range(2))
    return {"case": "CT head bone, EVM.from_mask(...).mesh()",
            "cold_first_call_s": cold["first_call_s"],
            "warm_first_call_s": warm["first_call_s"], "package_import_s": warm["import_s"],
            "compiled_call_s": warm_s}


def run(repeat):
    from skimage import __version__ as skimage_version
    from vtk import vtkVersion

    head, spacing = load("ct_head_invesalius")
    x, y, z = np.ogrid[: head.shape[0], : head.shape[1], : head.shape[2]]
    tools = {
        "box": np.broadcast_to((x >= 100) & (x < 180) & (y >= 80) & (y < 200) & (z >= 30)
                               & (z < 90), head.shape),
        "sphere": (x - 128) ** 2 + (y - 100) ** 2 + ((z - 54) * 1.5) ** 2 < 60 ** 2,
    }
    rows = []
    for label, threshold in (("skin", -500.0), ("bone", 300.0)):
        print(f"[bench] {label}: threshold {threshold} HU", flush=True)
        mask = head >= threshold
        row = {"case": label, **surface_row(head, spacing, threshold, repeat)}
        evm = EVM.from_mask(mask)
        for name, tool in tools.items():
            tool_evm = EVM.from_mask(tool)
            sweep_time, result = best_time(lambda: evm - tool_evm, repeat)
            dense_time, expected = best_time(lambda: EVM.from_mask(mask & ~tool), repeat)
            assert result == expected, "sweep and dense cut differ"
            row[f"cut_{name}_sweep_s"] = sweep_time
            row[f"cut_{name}_dense_s"] = dense_time
            row[f"cut_{name}_speedup_vs_dense"] = dense_time / sweep_time
        region = VolumeEVM.from_array(head, threshold, spacing=spacing)
        report = region.size_report()
        row["vevm_bytes"] = report["total_bytes"]
        row["dense_bytes"] = report["dense_bytes"]
        row["bytes_vs_dense"] = report["ratio"]
        rows.append(row)
    mri_rows = []
    for name, threshold in MRIS:
        print(f"[bench] {name}: threshold {threshold}", flush=True)
        mri_rows.append({"case": name, **surface_row(*load(name), threshold, repeat)})
    print("[bench] kernels' first use (two fresh processes)", flush=True)
    kernels = first_use(rows[1]["evm_extract_mesh_s"])
    return {"skimage": skimage_version, "vtk": vtkVersion.GetVTKVersion()}, rows, mri_rows, kernels


def print_table(rows, columns):
    for name, fmt in columns:
        print(f"{name:56s}" + "".join(f"{fmt.format(row[name]):>16s}" for row in rows))


SURFACE_COLUMNS = [
    ("case", "{}"), ("voxels", "{:,}"), ("extreme_vertices", "{:,}"), ("threads", "{}"),
    ("evm_extract_mesh_1thread_s", "{:.4f}"), ("evm_extract_mesh_s", "{:.4f}"),
    ("vtk_flying_edges_1thread_s", "{:.4f}"), ("vtk_flying_edges_s", "{:.4f}"),
    ("marching_cubes_s", "{:.4f}"),
    ("extract_mesh_speedup_vs_marching_cubes", "{:.1f}x"),
    ("extract_mesh_speedup_vs_vtk_flying_edges", "{:.2f}x"),
    ("extract_mesh_1thread_speedup_vs_vtk_flying_edges_1thread", "{:.2f}x"),
    ("mesh_faces_per_unit_face", "{:.3f}"),
]
CT_COLUMNS = [
    ("cut_box_sweep_s", "{:.4f}"), ("cut_box_dense_s", "{:.4f}"),
    ("cut_sphere_sweep_s", "{:.4f}"), ("cut_sphere_dense_s", "{:.4f}"),
    ("bytes_vs_dense", "{:.3f}"),
]


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    versions, rows, mri_rows, kernels = run(args.repeat)
    print_table(rows + mri_rows, SURFACE_COLUMNS)
    print_table(rows, CT_COLUMNS)
    print(json.dumps(kernels, indent=1))
    bone = next(r for r in rows if r["case"] == "bone")
    surfaces = rows + mri_rows
    checks = {
        "extract_mesh_speedup_vs_marching_cubes": min(r["extract_mesh_speedup_vs_marching_cubes"]
                                                      for r in surfaces),
        "extract_mesh_speedup_vs_vtk_flying_edges": min(
            r["extract_mesh_speedup_vs_vtk_flying_edges"] for r in surfaces),
        "mesh_faces_per_unit_face_bone": bone["mesh_faces_per_unit_face"],
        "bytes_vs_dense_bone": bone["bytes_vs_dense"],
    }
    for name, target in TARGETS.items():
        better = checks[name] >= target if "speedup" in name else checks[name] <= target
        print(f"target {name}: {checks[name]:.3f} (target {target}) "
              f"{'met' if better else 'NOT met'}")
    result = {
        "benchmark": "evm_core",
        **run_facts(),
        **versions,
        "timing": f"best of {args.repeat} calls, inputs built beforehand, kernels compiled",
        "targets": TARGETS,
        "measured": checks,
        "rows": rows,
        "mri_rows": mri_rows,
        "kernels": kernels,
    }
    write_json(args.out / "bench_evm.json", result)


if __name__ == "__main__":
    main()
