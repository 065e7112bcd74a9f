"""Rendering at scale: a method's first render's time and peak memory at 256³, 512³, 1024³
(issue 18): ray casting by default, shear-warp with ``--method shear_warp``.

The CT head of ../shared/data (256x256x108, int16) is resampled to ``n``³ by nearest neighbour
(same physical size, as ``bench_memory.upsampled_head`` makes its 512³), built at 300 HU and
saved as a ``.vevm`` in ``--work`` (kept there: later runs, and runs of other commits, reuse
it). Each size is then rendered in a fresh process, which loads the ``.vevm``, uses the
method's kernels once on a subsample of the CT head, of the same dtype (loading them is not
the render's cost) and times one ``render(..., method=method)`` of 512² pixels with the
orthographic oblique camera of ``bench_dvr`` and the ``ct_bone`` preset: the first render on
that VolumeEVM, which builds the method's tables (ray casting: the sampling table and the
space-leaping blocks; shear-warp: the principal axis's layout and classes). Peak RSS is the
process's high-water mark (``VmHWM``: the loaded VolumeEVM and the interpreter included;
``rss_before`` is the resident size just before the render). The image's SHA-256 is
recorded, so runs of two commits show whether their images are identical.

Results go under ``--label`` (e.g. ``before``, ``after``) in ``--out`` (default
``bench/results/<method>_scale.json``, merged with what the file holds already). The machine
is shared: read the times as indications.

Usage: ``python bench/bench_render_scale.py --label after [--method raycast|shear_warp]
[--sizes 256 512 1024] [--shading] [--work /tmp/raycast_scale] [--out FILE]``
"""

import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._common import run_facts, write_json  # noqa: E402

DATA = REPO.parent / "shared" / "data"
THRESHOLD = 300.0
PIXELS = 512


def build(size, path):
    """The CT head resampled to ``size``³ (nearest neighbour), its VolumeEVM saved to ``path``."""
    from volumeevm_addon import VolumeEVM

    meta = json.loads((DATA / "ct_head_invesalius.json").read_text())
    head = np.load(DATA / "ct_head_invesalius.npy")
    index = [(np.arange(size) * n) // size for n in head.shape]
    big = head[np.ix_(*index)].astype(np.int16)
    spacing = [s * n / size for s, n in zip(meta["spacing_mm"], head.shape)]
    start = time.perf_counter()
    vevm = VolumeEVM.from_array(big, THRESHOLD, spacing=spacing)
    seconds = time.perf_counter() - start
    del big
    vevm.save(path)
    return {"build_seconds": round(seconds, 2), "region_voxels": int(vevm.voxel_count)}


def rss(field):
    """A field of /proc/self/status (``VmRSS``, ``VmHWM``) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(field)


def render_once(path, method, shading):
    """The first render by ``method`` of the ``.vevm`` at ``path``: seconds, memory, checksum."""
    from bench.bench_dvr import cameras
    from volumeevm_addon import TransferFunction, VolumeEVM, grid_to_world, render

    tf = TransferFunction.preset("ct_bone")
    crop = np.load(DATA / "ct_head_invesalius.npy")[::8, ::8, ::4]  # the same dtype
    warm = VolumeEVM.from_array(crop, THRESHOLD)
    gw = grid_to_world(warm.spacing, warm.origin, warm.orientation)
    render(warm, cameras(warm.shape, gw, 16, 30.0, 20.0, False)["ortho"], tf, method=method,
           shading=shading)
    vevm = VolumeEVM.load(path)
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    cam = cameras(vevm.shape, g, PIXELS, 30.0, 20.0, False)["ortho"]
    before = rss("VmRSS")
    start = time.perf_counter()
    rgba, depth = render(vevm, cam, tf, method=method, shading=shading)
    seconds = time.perf_counter() - start
    digest = hashlib.sha256(rgba.tobytes() + depth.tobytes()).hexdigest()
    return {"seconds": round(seconds, 2), "peak_rss": rss("VmHWM"), "rss_before": before,
            "image_sha256": digest}


def child(args):
    """Run one step in a fresh process; its JSON result."""
    out = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True,
                         cwd=REPO)
    if out.returncode:
        raise RuntimeError(out.stderr)
    return json.loads(out.stdout.splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--label", default="after")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--method", default="raycast", choices=["raycast", "shear_warp"])
    parser.add_argument("--shading", action="store_true")
    parser.add_argument("--work", type=Path, default=Path("/tmp/raycast_scale"))
    parser.add_argument("--out", type=Path)
    parser.add_argument("--build", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--render", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.build:
        print(json.dumps(build(args.build, args.work / f"head{args.build}.vevm")))
        return
    if args.render:
        print(json.dumps(render_once(args.render, args.method, args.shading)))
        return
    args.out = args.out or REPO / "bench" / "results" / f"{args.method}_scale.json"
    args.work.mkdir(parents=True, exist_ok=True)
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    runs = results.setdefault(args.label + ("_shaded" if args.shading else ""), {})
    runs["facts"] = run_facts()
    for size in args.sizes:
        path = args.work / f"head{size}.vevm"
        facts = {}
        if not path.exists():
            facts = child(["--build", str(size), "--work", str(args.work)])
        row = child(["--render", str(path), "--method", args.method]
                    + (["--shading"] if args.shading else []))
        runs[str(size)] = {**facts, **row}
        print(f"[bench] {size}³ {args.method} {args.label}: {row['seconds']} s, peak RSS "
              f"{row['peak_rss'] / 2**30:.2f} GiB (before the render "
              f"{row['rss_before'] / 2**30:.2f} GiB)", flush=True)
        write_json(args.out, results)


if __name__ == "__main__":
    main()
