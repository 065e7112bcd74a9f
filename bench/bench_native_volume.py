"""Native Blender Volume: grid and file of the region, write time, and Cycles against the
reference DVR, on the CT head and the two MRIs.

Run with a bpy interpreter (either pinned line)::

    .venv/py313/bin/python bench/bench_native_volume.py [--samples 64] [--size 128]

For each volume: the region where its transfer function starts to be opaque (CT head >= 150 HU
with ct_bone; the MRIs from 15 % of their range with the mri preset), written as the native
Volume (best of 3: grid, file), sizes against the VolumeEVM's densities table, the refresh
after a transfer-function change, and the RMSE between Cycles (emission + absorption, CPU,
``--samples`` samples, no denoising) and the reference DVR of the same front view,
premultiplied RGBA at ``--size``². Results: ``bench/results/native_volume.json``.
"""

import argparse
import sys
import time

import numpy as np
from _common import REPO, best_time, run_facts, write_json

sys.path.insert(0, str(REPO / "tests"))
import bpy  # noqa: E402

from blender_helpers import addon, reset_blender  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CASES = (("ct_head_invesalius", "ct_bone", 150.0), ("mr_t1_itk_kmeans", "mri", None),
         ("mr_brainsmall_volpack", "mri", None))


def measure(ext, name, preset, threshold, size, samples):
    api, nv = ext.blender.api, ext.blender.native_volume
    reset_blender()
    vol = api.import_volume(DATA / f"{name}.npy")
    settings = bpy.context.scene.volumeevm_render
    api.load_preset(settings, preset, vol)
    if threshold is None:  # where the mri preset's opacity starts
        s = vol.volumeevm
        threshold = s.value_min + 0.15 * (s.value_max - s.value_min)
    api.build(vol, threshold)
    vevm = api.get_vevm(vol)
    api.make_volume_object(vol)  # first use: openvdb import, kernels
    write_s, native = best_time(lambda: api.make_volume_object(vol), 3)
    timing = nv.last_timing(vol)
    densities = vevm.table().nbytes
    tf = api.transfer_function(settings)
    api.set_transfer_function(settings, api.transfer_function(settings))  # same points: no-op
    points = np.array(tf.points)
    points[:, 4] *= 0.5
    start = time.perf_counter()
    api.set_transfer_function(settings, type(tf)(points, unit_length_mm=tf.unit_length_mm))
    bpy.context.view_layer.update()
    material_s = time.perf_counter() - start
    api.set_transfer_function(settings, tf)
    bpy.context.view_layer.update()
    scene = bpy.context.scene
    api.frame_volume(vol, "FRONT")
    r = scene.render
    r.resolution_x = r.resolution_y = size
    r.film_transparent, r.dither_intensity = True, 0.0
    scene.view_settings.view_transform = "Standard"
    r.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", samples, False
    start = time.perf_counter()
    cycles = ext.blender.scene.render_scene(scene).rgba
    cycles_s = time.perf_counter() - start
    native.hide_render = True
    start = time.perf_counter()
    reference = api.render_dvr(vol, tf, method="reference").dvr_rgba
    reference_s = time.perf_counter() - start
    errors = {}
    for factor in (1, 2, 4):
        shape = (size // factor, factor, size // factor, factor, 4)
        a, b = cycles.reshape(shape).mean((1, 3)), reference.reshape(shape).mean((1, 3))
        errors[f"{factor}x{factor}"] = float(np.sqrt(np.mean((a - b) ** 2)))
    return {
        "volume": name, "preset": preset, "threshold": float(threshold),
        "voxels": vevm.voxel_count, "densities_bytes": int(densities),
        "densities_dtype": str(vevm.table().dtype),
        "make_volume_object_s": write_s, "grid_s": timing["grid_s"], "write_s": timing["write_s"],
        "grid_bytes": timing["grid_bytes"], "file_bytes": timing["file_bytes"],
        "grid_over_densities": timing["grid_bytes"] / densities,
        "file_over_densities": timing["file_bytes"] / densities,
        "material_refresh_s": material_s,
        "cycles_s": cycles_s, "reference_s": reference_s, "samples": samples, "size": size,
        "rmse_rgba": errors, "mean_alpha": [float(cycles[..., 3].mean()),
                                            float(reference[..., 3].mean())],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--size", type=int, default=128)
    args = parser.parse_args()
    ext = addon()
    __import__(f"{ext.__name__}.blender.api")
    ext.register()
    rows = []
    for case in CASES:
        row = measure(ext, *case, args.size, args.samples)
        print(row, flush=True)
        rows.append(row)
    write_json(REPO / "bench" / "results" / "native_volume.json",
               {"facts": run_facts(), "bpy": bpy.app.version_string, "results": rows})


if __name__ == "__main__":
    main()
