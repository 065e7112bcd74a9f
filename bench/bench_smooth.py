"""Smooth display surface (``mesh(smooth=True)``) against the exact mesh and marching cubes.

On real masks (CT head at 300 HU, the CGAL skull at 2.9, liver label 127): the time of the
exact mesh and of the smooth one (best of N, warm kernels), the normals' roughness
(``tests/surface_helpers.roughness``: radians of turning per lattice unit of area) of the exact
mesh, the smooth one and scikit-image's marching cubes on the same mask, and the smooth mesh's
enclosed volume against the voxel count. Writes ``bench/results/bench_smooth.json``.

    .venv/py313/bin/python bench/bench_smooth.py [--repeat 5]
"""

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from bench._common import best_time, run_facts, write_json  # noqa: E402
from surface_helpers import enclosed_volume, marching_cubes, roughness, triangles  # noqa: E402
from volumeevm_addon import EVM  # noqa: E402

DATA = REPO.parent / "shared" / "data"


def masks():
    ct = np.load(DATA / "ct_head_invesalius.npy")
    yield "ct_head_300HU", ct >= 300
    yield "ct_skull_cgal_2.9", np.load(DATA / "ct_skull_cgal.npy") >= 2.9
    yield "seg_liver_cgal_127", np.load(DATA / "seg_liver_cgal.npy") == 127


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    results = {"facts": run_facts(), "cases": {}}
    for name, mask in masks():
        evm = EVM.from_mask(mask)
        evm.mesh(smooth=True)  # compile or load the kernels
        exact_s, (lattice, polygons) = best_time(evm.mesh, args.repeat)
        smooth_s, (moved, cut) = best_time(lambda: evm.mesh(smooth=True), args.repeat)
        case = {
            "voxels": int(mask.sum()), "exact_s": exact_s, "smooth_s": smooth_s,
            "smooth_over_exact": smooth_s / exact_s,
            "faces_exact": len(polygons), "faces_smooth": len(cut),
            "roughness_exact": roughness(lattice, triangles(lattice, polygons)),
            "roughness_smooth": roughness(moved, triangles(moved, cut)),
            "roughness_marching_cubes": roughness(*marching_cubes(mask)),
            "volume_smooth_over_voxels": enclosed_volume(moved, triangles(moved, cut)) / mask.sum(),
            "max_vertex_offset": float(np.abs(moved[:len(lattice)] - lattice).max()),
        }
        results["cases"][name] = case
        print(name, {k: round(v, 4) if isinstance(v, float) else v for k, v in case.items()},
              flush=True)
    write_json(REPO / "bench" / "results" / "bench_smooth.json", results)


if __name__ == "__main__":
    main()
