"""DVR speed against accuracy: every method over its quality settings, and the peers (issue 5).

For each dataset, one orthographic view (and the same view in perspective for the real volumes),
every method of ours is run over its own quality settings and the peers over theirs; each run
gives a frame time and the error of its image against the dense float64 reference renderer
(``method="reference"``, step voxel/16, no early termination) of the scene it was given. The
chart plots frame time against error (log-log), one colour per method with its Pareto front,
one panel per dataset; the summary gives, per dataset and method, the time to reach an error
≤ ε for ε = 0.02, 0.01, 0.005. Design: ``../shared/design/notes/dvr_evaluation.md`` §7.

Datasets (``DATASETS``): the real volumes of ``../shared/data`` (``brainsmall``: VolPack's own
MRI example; ``ct_head``: CT 256×256×108) and volumes made in code by
:mod:`volumeevm_addon.phantoms`, quantized to 8 bits so that every renderer, VolPack
included, reads the same integers: Gaussian blobs (smooth, closed form), Marschner–Lobb with a
narrow pulse (high frequency), a checkerboard (sharp edges), a thin spherical shell, band-limited
noise whose region of interest cuts through material (the region-boundary policy), and the
256³ timing volume.

Quality settings (``SWEEPS``; a setting a method does not accept is left out, so the bench runs
on any version of the renderers): ray casting: step, jitter, pre-integration, early-termination
threshold; shear-warp: intermediate image scale, interpolated slices per voxel slice, pre- or
post-classification; splatting: kernel radius and width, the cross-fade of sheet families
near the principal-axis switch, sub-slabs per sheet; VolPack: its defaults and the speed
settings its manual suggests; VTK ``vtkFixedPointVolumeRayCastMapper``: sample distance. How the
peers are matched to our scene is written in ``bench/peers/``. Our GPU method (Blender's ``gpu``
module) runs over its step in a Blender process of its own (``bench/peers/gpu_peer.py``),
labelled with the GPU that drew it (here Mesa llvmpipe: software OpenGL on the same CPU cores).

Error: RMSE over all pixels and the four channels of premultiplied RGBA (the primary measure of
the notes; ``image_errors`` gives the others, all in the CSV). Ours are compared with the
reference of the VolumeEVM they render (region of interest, boundary policy "clamp"); the peers
render the whole dense volume and are compared with the reference of the whole volume (for the
phantoms but ``noise_cut`` the region is the whole volume, so the two are the same). Peers'
images are 8-bit.

Timing: each setting is run once untimed (warm-up), then ``--repeat`` times (7: frames of a few
milliseconds vary by half from one call to the next on this shared machine, and a median of 3
follows that); the median and the inter-quartile range are reported. Apart from frame time:
building the VolumeEVM, and the method's first call on a fresh VolumeEVM and transfer function
(classification tables, gradients, the densities tables of other traversal orders: the
per-transfer-function and per-view preparation), the tables it built, and the peak of
Python/NumPy allocations during that call (``tracemalloc``) against the VolumeEVM's and the
dense volume's bytes; and each method's first use of its compiled kernels (:func:`first_use`: a
fresh process rendering the CT head with an empty kernel cache, which compiles, then one that
loads them from the cache). Our kernels run on ``kernel_threads()`` threads (all cores), VTK on
its default threads (all cores), VolPack on one. The machine has 2 cores shared with other work:
compare ratios within one run, not absolute numbers.
References are cached in ``bench/results/cache/`` keyed by the scene and
``volumeevm_addon/rendering/_reference.py``.

Outputs in ``--out``: ``speed_accuracy.csv`` (tidy, one row per run, with commit and
versions), ``speed_accuracy.png`` (the chart), ``speed_accuracy.md`` (the time-to-ε tables,
preparation and memory, the targets stated plainly), ``bench_dvr.json`` (the run's facts,
the datasets, scenes and preparation, the targets; the runs themselves are in the CSV) and
``dvr_<dataset>_<view>.png`` (each method's default image beside the reference).

Usage: ``python bench/bench_dvr.py [--out bench/results] [--repeat 7]
[--datasets blobs,ml41,...] [--methods ...] [--peers volpack,vtk] [--no-gpu] [--quick]``
"""

import argparse
import csv
import dataclasses
import hashlib
import io
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench" / "peers"))

from bench._common import accepts, non_default, run_facts, write_json  # noqa: E402
from volumeevm_addon import (  # noqa: E402
    METHODS,
    Camera,
    TransferFunction,
    VolumeEVM,
    grid_to_world,
    kernel_threads,
    phantoms,
    render,
)
from volumeevm_addon.metrics import image_errors  # noqa: E402
from volumeevm_addon.model import BLENDER_UNITS_PER_MM  # noqa: E402
from volumeevm_addon.system import write_atomically  # noqa: E402

DATA = REPO.parent / "shared" / "data"
OURS = tuple(m for m in METHODS if m != "reference")
EPSILONS = (0.02, 0.01, 0.005)
TARGETS = {"speedup_vs_vtk_at_vtk_error_at_least": 2.0,
           "shear_warp_time_over_volpack_at_volpack_error_at_most": 1.0}
"""Issue 11's targets: at VTK's error our fastest method at least 2x VTK's speed (every dataset,
both views); shear-warp at VolPack's error (or lower) within 1.0x VolPack's frame time."""


# ----------------------------------------------------------------------------- datasets
def _u8(volume):
    """A phantom's densities in [0, 1] as 8-bit integers 0..255 (what every renderer reads)."""
    return np.round(np.clip(volume.array, 0.0, 1.0) * 255.0).astype(np.uint8)


def _pulse(centre, width, alpha, rgb=(1.0, 0.9, 0.8)):
    """Opacity ``alpha`` per mm at ``centre`` falling linearly to 0 at ``centre ± width / 2``
    (8-bit data units)."""
    return TransferFunction([(centre - width / 2, *rgb, 0.0), (centre, *rgb, alpha),
                             (centre + width / 2, *rgb, 0.0)])


def _ramp(lo, hi, alpha, rgb=(0.9, 0.7, 0.5)):
    return TransferFunction([(lo, *rgb, 0.0), (hi, *rgb, alpha)])


def _real(file, preset, data_range):
    meta = json.loads((DATA / f"{file}.json").read_text())
    array = np.load(DATA / f"{file}.npy")
    tf = TransferFunction.preset(preset, data_range=data_range)
    return array, tuple(float(s) for s in meta["spacing_mm"]), tf


def _blobs():
    shape = (64, 64, 64)
    centres = ((22, 24, 30), (42, 36, 26), (30, 44, 40))
    vol = phantoms.gaussian_blobs(shape, centres, (6.0, 5.0, 7.0), (1.0, 0.8, 0.9))
    return _u8(vol), (1.0, 1.0, 1.0), phantoms.extinction_tf(0.08 / 255.0, 255.0)


DATASETS = {
    # name: (panel class, make() -> (uint8/int array, spacing, tf), region threshold or None for
    #        the whole volume, image size, azimuth, elevation, perspective view too)
    "blobs": ("smooth, closed form", _blobs, None, 256, 30.0, 20.0, False),
    "ml41": ("high frequency (Marschner-Lobb, pulse)",
             lambda: (_u8(phantoms.marschner_lobb(41)), (1.0, 1.0, 1.0),
                      _pulse(127.5, 25.5, 0.5)), None, 256, 30.0, 20.0, False),
    "checker": ("sharp edges (checkerboard)",
                lambda: (_u8(phantoms.checker((48, 48, 48), 8)), (1.0, 1.0, 1.0),
                         _ramp(100.0, 160.0, 0.15)), None, 256, 30.0, 20.0, False),
    "shell": ("thin (spherical shell)",
              lambda: (_u8(phantoms.shell((64, 64, 64), 24.0, 1.0)), (1.0, 1.0, 1.0),
                       _ramp(20.0, 255.0, 0.9)), None, 256, 30.0, 20.0, False),
    "noise_cut": ("region boundary (noise, region cuts material)",
                  lambda: (_u8(phantoms.noise((80, 80, 80), 3.0, 7)), (1.0, 1.0, 1.0),
                           _ramp(90.0, 200.0, 0.25)), 128, 256, 30.0, 20.0, False),
    "brainsmall": ("real: MRI (VolPack's example)",
                   lambda: _real("mr_brainsmall_volpack", "mri", (0, 202)), 20, 256, 30.0, 20.0,
                   True),
    "ct_head": ("real: CT head", lambda: _real("ct_head_invesalius", "ct_bone", None), -300, 512,
                215.0, 20.0, True),
    "timing256": ("256³ timing volume",
                  lambda: (_u8(phantoms.timing_volume(256)), (1.0, 1.0, 1.0),
                           _ramp(60.0, 200.0, 0.08)), None, 512, 30.0, 20.0, False),
}
QUICK = ("blobs", "ml41", "brainsmall")


# ----------------------------------------------------------------------------- settings
def _grid(**axes):
    """Every combination of the given option values, as option dicts."""
    out = [{}]
    for name, values in axes.items():
        out = [{**o, name: v} for o in out for v in values]
    return out


SWEEPS = {
    # step_mm is in voxels here (scaled by the smallest voxel size at run time)
    "raycast": (_grid(step_mm=(2.0, 1.0, 0.5, 0.25), jitter=(False, True))
                + _grid(step_mm=(2.0, 1.0, 0.5), preintegrate=(True,))
                + _grid(step_mm=(1.0,), termination=(0.95, 1.0))),
    "raycast_navigate": _grid(step_mm=(1.0, 0.5)),
    "shear_warp": _grid(intermediate_scale=(0.5, 1.0, 2.0), slices_per_voxel=(1, 2, 4),
                        classification=("pre", "post")),
    "splat": (_grid(kernel_radius=(1.0, 1.5, 2.0), kernel_sigma=(0.4, 0.6))
              + _grid(blend=(0.0,)) + _grid(substeps=(2, 3))),
}
GPU_SWEEP = [{}] + _grid(step_mm=(2.0, 1.0, 0.25))
"""The GPU method's settings (``step_mm`` in voxels as above; its default is half a voxel)."""
PEER_SWEEPS = {
    "volpack": ({"min_voxel_opacity": 0.0, "max_ray_opacity": 1.0},
                {"min_voxel_opacity": 0.05, "max_ray_opacity": 0.95}),
    "vtk": tuple({"sample_distance": s} for s in (2.0, 1.0, 0.5, 0.25)),
}


def settings(method, voxel_mm, quick):
    """The method's quality settings this version of it accepts (defaults first), as option
    dicts with ``step_mm`` in mm."""
    out, seen = [{}], {"{}"}
    for s in SWEEPS[method]:
        if not accepts(method, s):
            continue
        s = non_default(method, {k: (v * voxel_mm if k == "step_mm" else v)
                                 for k, v in s.items()})
        key = json.dumps(s, sort_keys=True)
        if key not in seen:
            seen.add(key)
            out.append(s)
    return out[:3] if quick else out


def label(options):
    if not options:
        return "default"
    return " ".join(f"{k}={round(v, 3) if isinstance(v, float) else v}"
                    for k, v in sorted(options.items()))


# ----------------------------------------------------------------------------- views
def look_from(center, azimuth, elevation, distance, up=(0.0, 0.0, 1.0), front=(0.0, -1.0, 0.0)):
    """Camera-to-world matrix at ``distance`` (BU) from ``center``, looking at it with ``up`` up:
    the camera sits in direction ``front`` turned by ``azimuth`` about ``up`` (towards
    ``up x front``) and raised by ``elevation`` towards ``up`` (degrees)."""
    az, el = np.radians(azimuth), np.radians(elevation)
    up = np.asarray(up, dtype=np.float64)
    front = np.asarray(front, dtype=np.float64)
    side = np.cross(up, front)
    back = np.cos(el) * (np.cos(az) * front + np.sin(az) * side) + np.sin(el) * up
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = right, up, back
    m[:3, 3] = center + distance * back
    return m


def box_corners(shape, g):
    n = np.asarray(shape, dtype=np.float64)
    c = np.array([[a, b, d, 1.0] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                  for d in (-0.5, n[2] - 0.5)])
    return (c @ g.T)[:, :3]


def cameras(shape, g, size, azimuth, elevation, perspective):
    """The oblique orthographic camera framing the volume's box, and the perspective one."""
    corners = box_corners(shape, g)
    center = corners.mean(axis=0)
    radius = float(np.linalg.norm(corners - center, axis=1).max())
    m = look_from(center, azimuth, elevation, 2.0 * radius)
    local = (corners - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T
    ortho_scale = 1.02 * 2.0 * float(np.abs(local[:, :2]).max())
    out = {"ortho": Camera.orthographic(m, ortho_scale, resolution_x=size, resolution_y=size,
                                        clip_start=0.001, clip_end=10.0 * radius)}
    if perspective:
        mp = look_from(center, azimuth, elevation, 2.5 * radius)
        local = (corners - mp[:3, 3]) @ np.linalg.inv(mp[:3, :3]).T
        tan_half = 1.02 * float(np.max(np.abs(local[:, :2]) / -local[:, 2:3]))
        out["persp"] = Camera.perspective(mp, 18.0 / tan_half, sensor_width=36.0,
                                          resolution_x=size, resolution_y=size,
                                          clip_start=0.001, clip_end=10.0 * radius)
    return out


def camera_record(cam):
    rec = {"projection": cam.projection, "matrix_world": np.round(cam.matrix_world, 9).tolist(),
           "size": [cam.width, cam.height]}
    if cam.is_ortho:
        rec["ortho_scale"] = cam.ortho_scale
    else:
        rec.update(lens_mm=cam.lens_mm, sensor_width=cam.sensor_width)
    return rec


# ----------------------------------------------------------------------------- reference cache
def _sha(data):
    return hashlib.sha256(data).hexdigest()


def reference(vevm, cam, tf, cache_dir, name):
    """The reference image of this VolumeEVM and view, from the cache or rendered and cached."""
    oracle = _sha((REPO / "volumeevm_addon" / "rendering" / "_reference.py").read_bytes())
    key_src = json.dumps({"camera": camera_record(cam), "tf": np.asarray(tf.points).tolist(),
                          "unit": tf.unit_length_mm, "shape": vevm.shape,
                          "spacing": vevm.spacing, "voxels": vevm.voxel_count,
                          "table": _sha(np.ascontiguousarray(vevm.table(0)).tobytes()),
                          "oracle": oracle}, sort_keys=True)
    key = _sha(key_src.encode())[:20]
    path = cache_dir / f"ref_{name}_{key}.npz"
    if path.exists():
        with np.load(path) as cached:
            return cached["rgba"], float(cached["seconds"])
    print(f"[bench_dvr]   rendering reference {name} (cached afterwards) ...", flush=True)
    t0 = time.perf_counter()
    rgba, _ = render(vevm, cam, tf, method="reference")
    seconds = time.perf_counter() - t0
    cache_dir.mkdir(parents=True, exist_ok=True)
    ignore = cache_dir / ".gitignore"
    if not ignore.exists():  # the cache never goes into git
        ignore.write_text("*\n")
    write_atomically(path, lambda temporary: np.savez(temporary, rgba=rgba, seconds=seconds,
                                                      key=key_src), overwrite=True)
    return rgba, seconds


# ----------------------------------------------------------------------------- measuring
FIRST_USE = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
import volumeevm_addon
volumeevm_addon.system.set_kernel_cache_dir(sys.argv[2])
from bench.bench_dvr import scene
vevm, cam, tf = scene(sys.argv[3], "ortho")
times = []
for _ in range(2):
    t0 = time.perf_counter()
    volumeevm_addon.render(vevm, cam, tf, method=sys.argv[4])
    times.append(time.perf_counter() - t0)
print(json.dumps({"first_call_s": times[0], "second_call_s": times[1]}))
"""


def scene(name, view):
    """``(vevm, camera, tf)`` of a dataset's view, as the bench renders it."""
    _, make, threshold, size, azimuth, elevation, persp = DATASETS[name]
    array, spacing, tf = make()
    region = float(array.min()) if threshold is None else threshold
    g = grid_to_world(spacing, (0.0, 0.0, 0.0))
    cam = cameras(array.shape, g, size, azimuth, elevation, persp)[view]
    return VolumeEVM.from_array(array, region, spacing=spacing), cam, tf


def first_use(methods, dataset="ct_head"):
    """Per method, its first renders of ``dataset`` (orthographic) in two fresh processes
    sharing a new kernel cache: the first compiles the kernels, the second loads them; each
    renders twice (the first call also builds the method's tables)."""
    out = {}
    for method in methods:
        print(f"[bench_dvr] first use of {method}'s kernels (two fresh processes)", flush=True)
        with tempfile.TemporaryDirectory() as cache:
            command = [sys.executable, "-c", FIRST_USE, str(REPO), cache, dataset, method]
            compiling, loading = (json.loads(subprocess.run(
                command, check=True, capture_output=True, text=True).stdout) for _ in range(2))
        out[method] = {"dataset": dataset, "compiling_first_call_s": compiling["first_call_s"],
                       "loading_first_call_s": loading["first_call_s"],
                       "second_call_s": loading["second_call_s"]}
    return out


def frame_times(call, repeat):
    """One untimed warm-up, then ``repeat`` timed calls: (median, IQR, last image)."""
    rgba = call()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        rgba = call()
        times.append(time.perf_counter() - t0)
    q1, med, q3 = np.percentile(times, (25, 50, 75))
    return float(med), float(q3 - q1), rgba


def preparation(make_vevm, make_tf, cam, method):
    """The first render on a fresh VolumeEVM and transfer function: its time, the bytes of
    the densities tables it holds afterwards (the first table and those built for the view) and
    the peak of allocations during it."""
    vevm, tf = make_vevm(), make_tf()
    tracemalloc.start()
    t0 = time.perf_counter()
    render(vevm, cam, tf, method=method)
    first = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"first_call_s": first, "peak_alloc_mb": peak / 2 ** 20,
            "tables_mb": vevm.size_report()["tables_bytes"] / 2 ** 20}


def gpu_rows(name, view, voxel_mm, repeat, base, ref, rows, images, info):
    """Our GPU method over :data:`GPU_SWEEP` in a Blender process (``peers/gpu_peer.py``):
    adds its rows, labelled with the GPU that drew them; a failure is reported, not hidden."""
    import gpu_peer

    settings_ = [{k: v * voxel_mm for k, v in s.items()} for s in GPU_SWEEP]
    try:
        renderer, results = gpu_peer.render(name, view, settings_, repeat)
    except RuntimeError as exc:
        print(f"[bench_dvr]   gpu failed: {exc}")
        info.setdefault("peer_failures", []).append(f"{name}/{view}/gpu: {exc}")
        return
    method = ("gpu (llvmpipe, software OpenGL)" if "llvmpipe" in renderer.lower()
              else f"gpu ({renderer})")
    info["gpu_renderer"] = renderer
    for options, result in zip(settings_, results):
        q1, med, q3 = np.percentile(result["frames_s"], (25, 50, 75))
        if not options:
            images["gpu"] = result["rgba"]
        rows.append({**base, "method": method, "kind": "gpu", "setting": label(options),
                     "options": options, "frame_s": float(med), "frame_iqr_s": float(q3 - q1),
                     **image_errors(result["rgba"], ref)})
        print(f"[bench_dvr]   gpu {label(options):55s} {med:8.4f} s  "
              f"RMSE {rows[-1]['rmse']:.5f}", flush=True)


def run_peer(peer, array, g, spacing, cam, tf, opts, repeat):
    if peer == "volpack":
        import volpack_peer

        reason = volpack_peer.available()
        if reason:
            raise RuntimeError(reason)
        return volpack_peer.render(array, g, spacing, cam, tf, frames=repeat, **opts)
    import vtk_peer

    return vtk_peer.render(array, g, cam, tf, mm_per_unit=1.0 / BLENDER_UNITS_PER_MM,
                           frames=repeat, **opts)


# ----------------------------------------------------------------------------- run
def run_dataset(name, args, rows, info):
    panel, make, threshold, size, azimuth, elevation, persp = DATASETS[name]
    array, spacing, tf0 = make()
    lowest = float(array.min())
    region = lowest if threshold is None else threshold
    t0 = time.perf_counter()
    vevm = VolumeEVM.from_array(array, region, spacing=spacing)
    build_s = time.perf_counter() - t0
    whole = vevm if threshold is None else VolumeEVM.from_array(array, lowest, spacing=spacing)
    sizes = vevm.size_report()
    g = grid_to_world(spacing, (0.0, 0.0, 0.0))
    voxel_mm = float(min(spacing))
    print(f"[bench_dvr] {name}: {array.shape} {array.dtype}, spacing {spacing} mm, region "
          f"{'all' if threshold is None else f'>= {threshold}'}, {size}^2", flush=True)
    info[name] = {"panel": panel, "shape": list(array.shape), "dtype": str(array.dtype),
                  "spacing_mm": list(spacing), "tf_points": np.asarray(tf0.points).tolist(),
                  "region_threshold": threshold, "region_voxels": vevm.voxel_count,
                  "voxels": int(array.size), "evm_vertices": len(vevm.evm),
                  "vevm_build_s": build_s, "vevm_bytes": sizes["total_bytes"],
                  "dense_bytes": sizes["dense_bytes"], "views": {}, "preparation": {}}
    for view, cam in cameras(array.shape, g, size, azimuth, elevation, persp).items():
        info[name]["views"][view] = camera_record(cam)
        print(f"[bench_dvr]  view {view} ({cam.width}x{cam.height})", flush=True)
        ref, ref_s = reference(vevm, cam, tf0, args.out / "cache", f"{name}_{view}")
        ref_whole, _ = (ref, ref_s) if whole is vevm else reference(
            whole, cam, tf0, args.out / "cache", f"{name}_{view}_whole")
        base = {"dataset": name, "panel": panel, "view": view, "size": f"{cam.width}x{cam.height}"}
        images = {"reference": ref}
        for method in args.methods:
            if view == "ortho":
                info[name]["preparation"][method] = preparation(
                    lambda: VolumeEVM.from_array(array, region, spacing=spacing),
                    lambda: dataclasses.replace(tf0), cam, method)
            for options in settings(method, voxel_mm, args.quick):
                med, iqr, rgba = frame_times(
                    lambda: render(vevm, cam, tf0, method=method, **options)[0], args.repeat)
                if not options:
                    images[method] = rgba
                rows.append({**base, "method": method, "kind": "ours", "setting": label(options),
                             "options": options, "frame_s": med, "frame_iqr_s": iqr,
                             **image_errors(rgba, ref)})
                print(f"[bench_dvr]   {method:17s} {label(options):55s} {med:8.4f} s  "
                      f"RMSE {rows[-1]['rmse']:.5f}", flush=True)
        if args.gpu:
            gpu_rows(name, view, voxel_mm, args.repeat, base, ref, rows, images, info)
        for peer in args.peers:
            if peer == "volpack" and not cam.is_ortho:
                continue  # VolPack has no perspective projection
            for opts in PEER_SWEEPS[peer]:
                try:
                    out = run_peer(peer, array, g, spacing, cam, tf0, opts, args.repeat)
                except Exception as exc:  # a peer that fails here is reported, not hidden
                    print(f"[bench_dvr]   {peer} {opts} failed: {type(exc).__name__}: {exc}")
                    info.setdefault("peer_failures", []).append(f"{name}/{view}/{peer}: {exc}")
                    continue
                rgba = out.pop("rgba")
                images.setdefault(peer, rgba)
                frames = out.get("frames_s") or [out["best_s"]]
                q1, med, q3 = np.percentile(frames, (25, 50, 75))
                rows.append({**base, "method": peer, "kind": "peer", "setting": label(opts),
                             "options": opts, "frame_s": float(med), "frame_iqr_s": float(q3 - q1),
                             "max_rss_mb": out.get("max_rss_kb", 0) / 1024.0,
                             "preprocess_s": out.get("classify_s"),
                             **image_errors(rgba, ref_whole)})
                print(f"[bench_dvr]   {peer:17s} {label(opts):55s} {med:8.4f} s  "
                      f"RMSE {rows[-1]['rmse']:.5f}", flush=True)
        if args.images:
            save_panel(args.out / f"dvr_{name}_{view}.png", images)


# ----------------------------------------------------------------------------- analysis
def pareto(points):
    """The points no other point beats in both time and error, by increasing time."""
    front, best = [], float("inf")
    for p in sorted(points, key=lambda r: (r["frame_s"], r["rmse"])):
        if p["rmse"] < best:
            front.append(p)
            best = p["rmse"]
    return front


def time_to_reach(points, eps):
    """The fastest point with error ≤ ``eps``, or None."""
    ok = [p for p in points if p["rmse"] <= eps]
    return min(ok, key=lambda r: r["frame_s"]) if ok else None


def groups(rows):
    """Rows by (dataset, view) and then by method."""
    out = {}
    for r in rows:
        out.setdefault((r["dataset"], r["view"]), {}).setdefault(r["method"], []).append(r)
    return out


def target_checks(rows):
    """The issue's two targets (:data:`TARGETS`) per dataset and view, stated plainly.

    VTK: the error of VTK at its default sample distance (1 voxel); our fastest point at that
    error against VTK's fastest point at that error (any sample distance). VolPack: our fastest
    shear-warp point at an error no higher than VolPack's (defaults), against VolPack's frame
    time."""
    out = []
    for (dataset, view), by in sorted(groups(rows).items()):
        entry = {"dataset": dataset, "view": view}
        vtk = [r for r in by.get("vtk", []) if r["options"].get("sample_distance") == 1.0]
        ours = [r for m, rs in by.items() if m in OURS for r in rs]
        if vtk and ours:
            v = time_to_reach(by["vtk"], vtk[0]["rmse"])
            best = time_to_reach(ours, v["rmse"])
            entry.update(vtk_s=v["frame_s"], vtk_rmse=v["rmse"], vtk_setting=v["setting"])
            if best:
                entry.update(best_at_vtk_error=f"{best['method']} {best['setting']}",
                             speedup_vs_vtk=v["frame_s"] / best["frame_s"],
                             vtk_target_met=v["frame_s"] / best["frame_s"]
                             >= TARGETS["speedup_vs_vtk_at_vtk_error_at_least"])
            else:
                entry.update(best_at_vtk_error=None, vtk_target_met=False)
        vp = [r for r in by.get("volpack", []) if r["options"].get("max_ray_opacity") == 1.0]
        if vp and by.get("shear_warp"):
            v = vp[0]
            best = time_to_reach(by["shear_warp"], v["rmse"])
            entry.update(volpack_s=v["frame_s"], volpack_rmse=v["rmse"])
            if best:
                entry.update(shear_warp_at_volpack_error=best["setting"],
                             shear_warp_time_over_volpack=best["frame_s"] / v["frame_s"],
                             volpack_target_met=best["frame_s"] / v["frame_s"]
                             <= TARGETS["shear_warp_time_over_volpack_at_volpack_error_at_most"])
            else:
                entry.update(shear_warp_at_volpack_error=None, volpack_target_met=False)
        out.append(entry)
    return out


# ----------------------------------------------------------------------------- outputs
COLOURS = {"shear_warp": "tab:blue", "splat": "tab:green", "raycast": "tab:orange",
           "raycast_navigate": "tab:brown", "volpack": "tab:red", "vtk": "tab:purple",
           "gpu": "tab:cyan"}
MARKERS = {"ours": "o", "peer": "s", "gpu": "^"}


def save_chart(path, rows):
    """Frame time against RMSE (log-log), one panel per dataset and view, each method's points
    and Pareto front; the joint front of ours dashed. Needs matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    panels = sorted(groups(rows).items())
    cols = min(3, len(panels))
    nrows = -(-len(panels) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 4.3 * nrows), squeeze=False)
    for ax, ((dataset, view), by) in zip(axes.flat, panels):
        for method, points in by.items():
            c = COLOURS.get(method.split(" ")[0], "black")
            marker = MARKERS[points[0]["kind"]]
            ax.scatter([p["frame_s"] for p in points], [max(p["rmse"], 1e-5) for p in points],
                       color=c, marker=marker, s=14, alpha=0.6)
            front = pareto(points)
            ax.plot([p["frame_s"] for p in front], [max(p["rmse"], 1e-5) for p in front],
                    color=c, marker=marker, ms=4, lw=1.3, label=method)
        joint = pareto([p for m, ps in by.items() if m in OURS for p in ps])
        ax.plot([p["frame_s"] for p in joint], [max(p["rmse"], 1e-5) for p in joint],
                color="black", ls="--", lw=0.8, label="ours: joint front")
        for eps in EPSILONS:
            ax.axhline(eps, color="grey", lw=0.5, ls=":")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("frame time (s, median)")
        ax.set_ylabel("RMSE, premultiplied RGBA vs reference")
        ax.set_title(f"{dataset} ({view}): {by[next(iter(by))][0]['panel']}", fontsize=8)
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=6, loc="best")
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    fig.suptitle("VolumeEVM DVR: frame time against error, each method over its quality "
                 "settings (lines: Pareto fronts; dotted: ε = 0.02, 0.01, 0.005)", fontsize=9)
    fig.tight_layout()
    write_atomically(path, lambda temporary: fig.savefig(temporary, dpi=80, format="png"),
                     overwrite=True)
    plt.close(fig)
    return True


def save_panel(path, images, columns=4):
    """Images in a grid over black (premultiplied RGB is the composite over black), labelled."""
    try:
        from PIL import Image, ImageDraw
    except ImportError:
        return
    tiles = []
    for name, rgba in images.items():
        rgb = (np.clip(rgba[..., :3], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        tile = Image.fromarray(rgb)
        ImageDraw.Draw(tile).text((4, 4), name, fill=(255, 255, 0))
        tiles.append(tile)
    w, h = tiles[0].size
    cols = min(columns, len(tiles))
    panel = Image.new("RGB", (w * cols, h * -(-len(tiles) // cols)))
    for i, tile in enumerate(tiles):
        panel.paste(tile, ((i % cols) * w, (i // cols) * h))
    if panel.width > 1024:
        f = 1024 / panel.width
        panel = panel.resize((1024, max(1, int(panel.height * f))))
    write_atomically(path, lambda temporary: panel.save(temporary, format="PNG"), overwrite=True)


CSV_FIELDS = ("dataset", "view", "size", "method", "kind", "setting", "frame_s", "frame_iqr_s",
              "rmse", "psnr", "rmse_alpha", "max_abs", "mae", "rmse_foreground", "max_rss_mb",
              "preprocess_s")


def write_csv(path, rows, facts):
    """The tidy table: one row per (dataset, view, method, setting), with the run's facts."""
    extra = {"commit": facts["commit"], "python": facts["python"], "numpy": facts["numpy"],
             "vtk": facts["versions"].get("vtk"),
             "libvolpack1_dev": facts["versions"].get("libvolpack1-dev"),
             "cpu": facts["machine"], "load_average": facts["load_average_at_start"]}
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_FIELDS + tuple(extra), extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({**r, **extra})
    write_atomically(path, lambda temporary: temporary.write_text(buf.getvalue()),
                     overwrite=True)


def read_csv(path):
    """The rows of a ``speed_accuracy.csv`` written by :func:`write_csv`, with the frame time
    and the error as numbers (the columns the time-to-ε tables and the chart read)."""
    with open(path, newline="") as file:
        rows = list(csv.DictReader(file))
    for r in rows:
        r["frame_s"] = float(r["frame_s"])
        r["rmse"] = float(r["rmse"])
    return rows


def _ms(seconds):
    return f"{seconds * 1000:.0f} ms" if seconds < 10 else f"{seconds:.1f} s"


def time_table(by):
    """The Markdown lines of one time-to-ε table: per method (``by``: method → rows of one
    dataset and view), the fastest setting reaching each ε and the lowest error reached.
    Used by the summary and by ``bench/readme_tables.py``."""
    lines = ["| method | " + " | ".join(f"RMSE ≤ {e}" for e in EPSILONS)
             + " | lowest RMSE (time) |", "|---" * (len(EPSILONS) + 2) + "|"]
    for method, points in by.items():
        cells = []
        for eps in EPSILONS:
            p = time_to_reach(points, eps)
            cells.append(f"{_ms(p['frame_s'])} ({p['setting']})" if p else "—")
        low = min(points, key=lambda r: r["rmse"])
        lines.append(f"| {method} | " + " | ".join(cells)
                     + f" | {low['rmse']:.4f} ({_ms(low['frame_s'])}) |")
    return lines


def summary(rows, info, checks, facts):
    """The Markdown summary: time to reach each ε per dataset and method, preparation and
    memory, and the targets."""
    lines = [f"# DVR speed against accuracy (commit {facts['commit'][:10]}, "
             f"{facts['date_utc']})", "",
             f"{facts['machine']}; Python {facts['python']}, NumPy {facts['numpy']}, "
             f"VTK {facts['versions'].get('vtk')}, libvolpack1-dev "
             f"{facts['versions'].get('libvolpack1-dev')}; load average "
             f"{facts['load_average_at_start']} at start; our kernels on {facts['threads']} "
             "threads, VTK on its default threads, VolPack on one. "
             "Frame time: median of the timed runs. "
             "Error: RMSE of premultiplied RGBA against the reference renderer. "
             "A cell gives the frame time of the fastest setting that reaches the error "
             "(and that setting); — = no setting does.", ""]
    for (dataset, view), by in sorted(groups(rows).items()):
        lines += [f"## {dataset} ({view}): {info[dataset]['panel']}", "",
                  *time_table(by), ""]
    lines += ["## Preparation and memory (first call on a fresh VolumeEVM, orthographic view)", "",
              "| dataset | VolumeEVM build | VolumeEVM / dense bytes | method | first call "
              "| densities tables after it | peak allocations |", "|---|---|---|---|---|---|---|"]
    for dataset, d in info.items():
        if not isinstance(d, dict) or "preparation" not in d:
            continue
        for method, p in d["preparation"].items():
            lines.append(f"| {dataset} | {_ms(d['vevm_build_s'])} | "
                         f"{d['vevm_bytes'] / 2**20:.1f} / {d['dense_bytes'] / 2**20:.1f} MB | "
                         f"{method} | {_ms(p['first_call_s'])} | "
                         f"{p['tables_mb']:.1f} MB | "
                         f"{p['peak_alloc_mb']:.0f} MB |")
    lines += ["", "## Kernels' first use (fresh processes, orthographic view)", "",
              "| method | dataset | first call, empty kernel cache (compiling) "
              "| first call, kernels loaded from the cache | second call |",
              "|---|---|---|---|---|"]
    for method, f in facts.get("first_use", {}).items():
        lines.append(f"| {method} | {f['dataset']} | {_ms(f['compiling_first_call_s'])} | "
                     f"{_ms(f['loading_first_call_s'])} | {_ms(f['second_call_s'])} |")
    lines += ["", "## Targets", ""]
    for c in checks:
        parts = []
        if "vtk_target_met" in c:
            if c.get("best_at_vtk_error"):
                parts.append(f"at VTK's error ({c['vtk_rmse']:.4f}, {_ms(c['vtk_s'])} with "
                             f"{c['vtk_setting']}) our "
                             f"fastest is {c['best_at_vtk_error']}: "
                             f"{c['speedup_vs_vtk']:.2f}× VTK's speed "
                             f"({'met' if c['vtk_target_met'] else 'NOT met'})")
            else:
                parts.append(f"no setting of ours reaches VTK's error {c['vtk_rmse']:.4f} "
                             "(NOT met)")
        if "volpack_target_met" in c:
            if c.get("shear_warp_at_volpack_error"):
                parts.append(f"shear-warp at VolPack's error ({c['volpack_rmse']:.4f}, "
                             f"{_ms(c['volpack_s'])}): "
                             f"{c['shear_warp_time_over_volpack']:.1f}× VolPack's frame time "
                             f"({'met' if c['volpack_target_met'] else 'NOT met'})")
            else:
                parts.append(f"no shear-warp setting reaches VolPack's error "
                             f"{c['volpack_rmse']:.4f} (NOT met)")
        if parts:
            lines.append(f"- **{c['dataset']} ({c['view']})**: " + "; ".join(parts) + ".")
    return "\n".join(lines) + "\n"


def versions():
    out = {"python": platform.python_version(), "numpy": np.__version__}
    try:
        from importlib.metadata import version

        out["vtk"] = version("vtk")
    except Exception:
        out["vtk"] = None
    q = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "libvolpack1-dev"],
                       capture_output=True, text=True)
    out["libvolpack1-dev"] = q.stdout.strip() or None
    return out


def cpu_model():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--repeat", type=int, default=7, help="timed runs per setting")
    parser.add_argument("--datasets", default=",".join(DATASETS))
    parser.add_argument("--methods", default=",".join(OURS))
    parser.add_argument("--peers", default="volpack,vtk", help="'' for none")
    parser.add_argument("--quick", action="store_true",
                        help=f"datasets {','.join(QUICK)} unless given, 3 settings per method")
    parser.add_argument("--no-images", dest="images", action="store_false")
    parser.add_argument("--no-gpu", dest="gpu", action="store_false",
                        help="leave out the GPU method (it needs the bpy module)")
    args = parser.parse_args()
    names = [d for d in args.datasets.split(",") if d]
    if args.quick and args.datasets == parser.get_default("datasets"):
        names = list(QUICK)
    args.methods = [m for m in args.methods.split(",") if m]
    args.peers = [p for p in args.peers.split(",") if p]
    args.out.mkdir(parents=True, exist_ok=True)
    facts = {**run_facts(), "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
                                       f"{cpu_model()}", "versions": versions(),
             "threads": kernel_threads()}
    rows, info = [], {}
    for name in names:
        run_dataset(name, args, rows, info)
    facts["first_use"] = first_use(args.methods)
    checks = target_checks(rows)
    text = summary(rows, info, checks, facts)
    print()
    print(text)
    write_atomically(args.out / "speed_accuracy.md", lambda t: t.write_text(text), overwrite=True)
    write_csv(args.out / "speed_accuracy.csv", rows, facts)
    if args.images and save_chart(args.out / "speed_accuracy.png", rows):
        print(f"wrote {args.out / 'speed_accuracy.png'}")
    write_json(args.out / "bench_dvr.json", {
        "benchmark": "dvr speed against accuracy", **facts,
        "load_average_end": round(os.getloadavg()[0], 2),
        "timing": f"median of {args.repeat} timed runs after one warm-up, "
                  f"{facts['threads']} kernel threads",
        "error": "RMSE etc. of premultiplied RGBA; ours vs the reference of the VolumeEVM, "
                 "peers vs the reference of the whole volume; peers' 8-bit images /255",
        "targets": TARGETS, "target_results": checks, "datasets": info})


if __name__ == "__main__":
    main()
