"""Shading before and after the gradient estimator of issue 21 (point 7): pictures, image errors
and frame times.

Run once per version of the renderers, each from its own checkout (``_common`` imports the
checkout the script is in), writing into one folder::

    python bench/shading_pictures.py after bench/results [--data FOLDER] [--parts ...]
    python <checkout of eae6980>/bench/shading_pictures.py before bench/results [...]

(the data folder defaults to ``../shared/data`` beside the checkout; ``--parts`` picks some of
``pictures errors timings``, the results of the others already in the JSON file are kept).

Pictures: the CT head (bone preset, full resolution, the face) and the T1 MRI (``mri`` preset,
the side), ray cast with shading (``Shading()`` defaults) at 320x320 →
``shading_<volume>_<label>.png``.
Errors: each CPU method's shaded image of the CT head (every 2nd voxel, 120x100 pixels) against
the reference renderer, whose gradients are the same estimator's: mean and 99th percentile of
the per-pixel largest channel error, and RMSE. Timing: a shaded 256x256 frame of the full CT
head per method with 1 and 2 kernel threads: the first on a fresh VolumeEVM (gradients made)
and a later one (the best of 3). Results: ``shading_<label>.json``.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from _common import REPO, best_time, run_facts, write_json

from volumeevm_addon import (
    Camera,
    TransferFunction,
    VolumeEVM,
    grid_to_world,
    render,
    set_kernel_threads,
    write_png,
)
from volumeevm_addon.metrics import rmse

DATA = REPO.parent / "shared" / "data"
METHODS = (("raycast", {}), ("raycast_navigate", {}), ("splat", {}), ("shear_warp", {}),
           ("shear_warp post", {"classification": "post"}))


def load(name, step=1):
    """A volume of the data folder as a VolumeEVM of its voxels above its threshold."""
    meta = json.loads((DATA / f"{name}.json").read_text())
    array = np.load(DATA / f"{name}.npy")[::step, ::step, ::step]
    threshold = -300 if meta["modality"] == "CT" else 0.2 * meta["value_range"][1]
    spacing = np.array(meta["spacing_mm"]) * step
    return VolumeEVM.from_array(array, threshold, spacing=tuple(spacing)), meta


def view(vevm, size, direction):
    """An orthographic camera looking at the volume's centre along ``-direction``, framing
    it."""
    g = grid_to_world(vevm.spacing, vevm.origin)
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0)
    extent = float(np.linalg.norm(g[:3, :3] @ np.array(vevm.shape)))
    eye = centre + extent * np.asarray(direction)
    return Camera.look_at(eye, centre, (0.0, 0.0, 1.0), kind="ORTHO", ortho_scale=0.8 * extent,
                          resolution_x=size[0], resolution_y=size[1], clip_start=1e-4), g


def tf_of(meta):
    """The transfer function of a volume: CT bone, or the MRI preset over its value range."""
    if meta["modality"] == "CT":
        return TransferFunction.preset("ct_bone")
    return TransferFunction.preset("mri", data_range=meta["value_range"])


def pictures(label, out):
    """The CT head's and the MRI's shaded pictures."""
    for name, direction in (("ct_head_invesalius", (0.35, 1.0, 0.15)),
                            ("mr_t1_itk_kmeans", (1.0, 0.0, 0.1))):
        vevm, meta = load(name)
        cam, _ = view(vevm, (320, 320), direction)
        rgba, _ = render(vevm, cam, tf_of(meta), method="raycast", shading=True)
        write_png(out / f"shading_{name}_{label}.png", rgba, overwrite=True)


def errors():
    """Each method's error against the reference, shaded, on the CT head."""
    vevm, meta = load("ct_head_invesalius", 2)
    cam, _ = view(vevm, (120, 100), (0.3, -1.0, 0.25))
    tf = tf_of(meta)
    ref, _ = render(vevm, cam, tf, method="reference", shading=True)
    found = {}
    for label, options in METHODS:
        method = label.split()[0]
        rgba, _ = render(vevm, cam, tf, method=method, shading=True, **options)
        err = np.abs(rgba - ref).max(axis=-1)
        found[label] = {"mean": float(err.mean()), "p99": float(np.percentile(err, 99)),
                        "rmse": float(rmse(rgba, ref))}
        print(label, found[label], flush=True)
    return found


def timings():
    """Each method's shaded frame times, first and later, with 1 and 2 threads."""
    small, meta = load("ct_head_invesalius", 4)
    cam, _ = view(small, (16, 16), (0.3, -1.0, 0.25))
    for label, options in METHODS:  # compile the kernels first
        render(small, cam, tf_of(meta), method=label.split()[0], shading=True, **options)
    found = {}
    for threads in (1, 2):
        set_kernel_threads(threads)
        for label, options in METHODS:
            method = label.split()[0]
            vevm, meta = load("ct_head_invesalius")
            cam, _ = view(vevm, (256, 256), (0.3, -1.0, 0.25))
            tf = tf_of(meta)
            start = time.perf_counter()
            render(vevm, cam, tf, method=method, shading=True, **options)
            first = time.perf_counter() - start
            later, _ = best_time(
                lambda: render(vevm, cam, tf, method=method, shading=True, **options), 3)
            found[f"{label}, {threads} threads"] = {"first_s": first, "later_s": later}
            print(label, threads, found[f"{label}, {threads} threads"], flush=True)
    return found


def main():
    global DATA
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("label")
    parser.add_argument("out", type=Path)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--parts", nargs="+", default=["pictures", "errors", "timings"],
                        choices=["pictures", "errors", "timings"])
    args = parser.parse_args()
    DATA = args.data
    path = args.out.resolve() / f"shading_{args.label}.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    facts = run_facts()
    results.setdefault("facts", {}).update({part: facts for part in args.parts})
    if "pictures" in args.parts:
        pictures(args.label, args.out.resolve())
    for part, function in (("errors", errors), ("timings", timings)):
        if part in args.parts:
            results[part] = function()
            write_json(path, results)


if __name__ == "__main__":
    main()
