"""Benchmark of the EVM core against its peers, side by side in one run (issue 2).

On the CT head of ../shared/data at a skin and a bone threshold:

- EVM extraction + mesh against scikit-image ``marching_cubes`` on the same threshold;
- mesh polygons against unit boundary faces;
- EVM Boolean (section sweep) against a dense NumPy Boolean + re-extraction, cutting by a box
  and by a sphere;
- VolumeEVM bytes against the dense array.

Each timing is the best of ``--repeat`` runs of the call alone (inputs built beforehand). Prints a
table and writes JSON (with versions and commit) to ``--out``.

Usage: ``python bench/bench_evm.py --out bench/results``
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._common import best_time, run_facts, write_json  # noqa: E402
from volumeevm_addon import EVM, VolumeEVM  # noqa: E402

DATA = REPO.parent / "shared" / "data"
TARGETS = {"extract_mesh_speedup_vs_marching_cubes": 3.0, "mesh_faces_per_unit_face_bone": 0.4,
           "bytes_vs_dense_bone": 0.35}


def unit_faces(mask):
    padded = np.pad(mask, 1).astype(np.int8)
    return sum(int(np.count_nonzero(np.diff(padded, axis=axis))) for axis in range(3))


def run(repeat):
    from skimage import __version__ as skimage_version
    from skimage.measure import marching_cubes

    meta = json.loads((DATA / "ct_head_invesalius.json").read_text())
    head = np.load(DATA / "ct_head_invesalius.npy")
    spacing = tuple(meta["spacing_mm"])
    as_float = head.astype(np.float32)
    x, y, z = np.ogrid[: head.shape[0], : head.shape[1], : head.shape[2]]
    tools = {
        "box": np.broadcast_to((x >= 100) & (x < 180) & (y >= 80) & (y < 200) & (z >= 30) & (z < 90), head.shape),
        "sphere": (x - 128) ** 2 + (y - 100) ** 2 + ((z - 54) * 1.5) ** 2 < 60 ** 2,
    }
    rows = []
    for label, threshold in (("skin", -500.0), ("bone", 300.0)):
        print(f"[bench] {label}: threshold {threshold} HU", flush=True)
        mask = head >= threshold

        def extract_and_mesh():
            return EVM.from_mask(head >= threshold).mesh()

        evm_time, (_, polygons) = best_time(extract_and_mesh, repeat)
        mc_time, (_, mc_faces, _, _) = best_time(
            lambda: marching_cubes(as_float, level=threshold, spacing=spacing), repeat)
        evm = EVM.from_mask(mask)
        row = {
            "case": label,
            "threshold_hu": threshold,
            "voxels": int(np.count_nonzero(mask)),
            "extreme_vertices": len(evm),
            "evm_extract_mesh_s": evm_time,
            "marching_cubes_s": mc_time,
            "extract_mesh_speedup_vs_marching_cubes": mc_time / evm_time,
            "mesh_polygons": len(polygons),
            "marching_cubes_triangles": len(mc_faces),
            "unit_faces": unit_faces(mask),
        }
        row["mesh_faces_per_unit_face"] = row["mesh_polygons"] / row["unit_faces"]
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
    return {"skimage": skimage_version}, rows


def print_table(rows):
    columns = [
        ("case", "{}"), ("voxels", "{:,}"), ("extreme_vertices", "{:,}"),
        ("evm_extract_mesh_s", "{:.3f}"), ("marching_cubes_s", "{:.3f}"),
        ("extract_mesh_speedup_vs_marching_cubes", "{:.1f}x"),
        ("mesh_faces_per_unit_face", "{:.3f}"),
        ("cut_box_sweep_s", "{:.4f}"), ("cut_box_dense_s", "{:.4f}"),
        ("cut_sphere_sweep_s", "{:.4f}"), ("cut_sphere_dense_s", "{:.4f}"),
        ("bytes_vs_dense", "{:.3f}"),
    ]
    for name, fmt in columns:
        print(f"{name:42s}" + "".join(f"{fmt.format(row[name]):>14s}" for row in rows))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    versions, rows = run(args.repeat)
    print_table(rows)
    bone = next(r for r in rows if r["case"] == "bone")
    checks = {
        "extract_mesh_speedup_vs_marching_cubes": min(r["extract_mesh_speedup_vs_marching_cubes"] for r in rows),
        "mesh_faces_per_unit_face_bone": bone["mesh_faces_per_unit_face"],
        "bytes_vs_dense_bone": bone["bytes_vs_dense"],
    }
    for name, target in TARGETS.items():
        better = checks[name] >= target if "speedup" in name else checks[name] <= target
        print(f"target {name}: {checks[name]:.3f} (target {target}) {'met' if better else 'NOT met'}")
    result = {
        "benchmark": "evm_core",
        **run_facts(),
        **versions,
        "timing": f"best of {args.repeat} calls, inputs built beforehand",
        "targets": TARGETS,
        "measured": checks,
        "rows": rows,
    }
    write_json(args.out / "bench_evm.json", result)


if __name__ == "__main__":
    main()
