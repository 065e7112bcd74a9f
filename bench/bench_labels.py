"""Benchmark of label maps (issue 22): every label in one sweep, and per-label meshes against
their peers, side by side in one run.

Maps: the real liver label map of ../shared/data (4 labels, 438 x 353 x 165) and synthetic
Voronoi maps at 256³ with 10 and 100 cells (every voxel labelled by its nearest of N random
seeds, seed 0; uint8).

- ``VolumeEVM.from_labels`` (one sweep, every label) against one ordinary build on the same grid
  (``from_array(map, 1)``: the whole foreground as one region) and against one band build per
  label (what a user did before), on one thread and on all (``kernel_threads``);
- per-label meshes: every label's exact closed mesh (``LabelSet.meshes``, made together so that
  touching labels share their polygons: what Make Label Meshes shows) against
  scikit-image's ``marching_cubes`` run per label on the label's mask (one thread; the peer the
  issue names) and zmesh's multi-label marching cubes (``Mesher``, all labels in one call; the
  mesher Microscopy Nodes uses), on one thread.
- tracemalloc peak of ``from_labels`` (the kernels' arrays included) against the map's bytes.

Each timing is the best of ``--repeat`` runs (kernels compiled by a first call, whose time is
reported as ``first_call_s``). Prints a table and writes JSON to ``--out``.

Usage: ``python bench/bench_labels.py --out bench/results`` (zmesh from requirements/bench.txt)
"""

import argparse
import json
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._common import best_time, run_facts, write_json  # noqa: E402
from volumeevm_addon import VolumeEVM, kernel_threads, set_kernel_threads  # noqa: E402

DATA = REPO.parent / "shared" / "data"
TARGETS = {"from_labels_vs_one_build": 1.5, "mesh_speedup_vs_marching_cubes": 3.0}


def voronoi(n_cells, size=256, seed=0):
    """A ``size``³ uint8 map: each voxel the number (1..n) of its nearest of n random seeds."""
    from scipy.spatial import cKDTree

    seeds = np.random.default_rng(seed).uniform(0, size, (n_cells, 3))
    grid = np.indices((size, size, size), dtype=np.float32).reshape(3, -1).T
    _, nearest = cKDTree(seeds).query(grid, workers=1)
    return (nearest + 1).astype(np.uint8).reshape(size, size, size)


def maps():
    meta = json.loads((DATA / "seg_liver_cgal.json").read_text())
    yield "liver (4 labels)", np.load(DATA / "seg_liver_cgal.npy"), tuple(meta["spacing_mm"])
    for n in (10, 100):
        yield f"voronoi 256³ ({n} labels)", voronoi(n), (1.0, 1.0, 1.0)


def build_row(name, array, spacing, repeat, threads):
    start = time.perf_counter()
    regions = VolumeEVM.from_labels(array, spacing=spacing)
    first = time.perf_counter() - start
    row = {"map": name, "shape": list(array.shape), "labels": len(regions), "first_call_s": first,
           "threads": {}}
    for count in threads:
        set_kernel_threads(count)
        labels_s, _ = best_time(lambda: VolumeEVM.from_labels(array, spacing=spacing), repeat)
        one_s, _ = best_time(lambda: VolumeEVM.from_array(array, 1, spacing=spacing), repeat)
        bands_s, _ = best_time(lambda: [VolumeEVM.from_array(array, label, upper=label,
                                                             spacing=spacing)
                                        for label in regions], 1)
        row["threads"][count] = {"from_labels_s": labels_s, "one_build_s": one_s,
                                 "band_builds_s": bands_s, "vs_one_build": labels_s / one_s,
                                 "speedup_vs_band_builds": bands_s / labels_s}
    set_kernel_threads(None)
    tracemalloc.start()
    VolumeEVM.from_labels(array, spacing=spacing)
    row["peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    row["map_mib"] = array.nbytes / 2**20
    return row, regions


def mesh_row(name, array, spacing, regions, repeat):
    from skimage.measure import marching_cubes

    set_kernel_threads(1)
    ours_s, meshes = best_time(lambda: list(regions.meshes().values()), repeat)
    set_kernel_threads(None)

    def per_label_marching_cubes():
        for label in regions:
            marching_cubes(np.pad(array == label, 1).astype(np.uint8), 0.5, spacing=spacing)

    mc_s, _ = best_time(per_label_marching_cubes, 1 if array.size > 2e7 else repeat)
    row = {"map": name, "ours_1_thread_s": ours_s, "marching_cubes_per_label_s": mc_s,
           "speedup_vs_marching_cubes": mc_s / ours_s,
           "our_faces": int(sum(len(polygons) for _, polygons in meshes))}
    try:
        import zmesh
    except ImportError:
        row["zmesh_s"] = None
        return row
    mesher = zmesh.Mesher(spacing)

    def run_zmesh():
        mesher.mesh(np.asfortranarray(array), close=True)
        out = [mesher.get(label, normals=False) for label in mesher.ids()]
        mesher.clear()
        return out

    zmesh_s, zmeshes = best_time(run_zmesh, repeat)
    row.update(zmesh_s=zmesh_s, speedup_vs_zmesh=zmesh_s / ours_s,
               zmesh_triangles=int(sum(len(m.faces) for m in zmeshes)))
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    facts = run_facts()
    threads = sorted({1, kernel_threads()})
    builds, meshes = [], []
    for name, array, spacing in maps():
        row, regions = build_row(name, array, spacing, args.repeat, threads)
        builds.append(row)
        meshes.append(mesh_row(name, array, spacing, regions, args.repeat))
        print(f"{name}: from_labels {row['threads'][threads[-1]]['from_labels_s']:.3f} s, "
              f"{row['threads'][threads[-1]]['vs_one_build']:.2f}x one build; meshes "
              f"{meshes[-1]['speedup_vs_marching_cubes']:.1f}x marching cubes", flush=True)
    print(f"\n{'map':26} {'thr':>3} {'labels s':>9} {'one s':>7} {'ratio':>6} {'bands s':>8} "
          f"{'peak MiB':>9}")
    for row in builds:
        for count, t in row["threads"].items():
            print(f"{row['map']:26} {count:>3} {t['from_labels_s']:9.3f} {t['one_build_s']:7.3f} "
                  f"{t['vs_one_build']:6.2f} {t['band_builds_s']:8.3f} {row['peak_mib']:9.1f}")
    print(f"\n{'map':26} {'ours s':>7} {'mc s':>7} {'x mc':>6} {'zmesh s':>8} {'x zmesh':>8}")
    for row in meshes:
        z = row.get("zmesh_s")
        print(f"{row['map']:26} {row['ours_1_thread_s']:7.3f} "
              f"{row['marching_cubes_per_label_s']:7.3f} "
              f"{row['speedup_vs_marching_cubes']:6.1f} "
              + (f"{z:8.3f} {row['speedup_vs_zmesh']:8.2f}" if z else f"{'-':>8} {'-':>8}"))
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "bench_labels.json", {"facts": facts, "targets": TARGETS,
                                                "builds": builds, "meshes": meshes})


if __name__ == "__main__":
    main()
