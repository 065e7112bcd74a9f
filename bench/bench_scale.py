"""Scale: chunked builds from OME-Zarr stores of N³ voxels against Dask's bare read (issue 18).

The CT head of ../shared/data (int16 HU, kept int16: the threshold stays 300 HU) is resampled by
nearest neighbour to N³ and written chunk by chunk (128³ chunks, blosc-zstd, NGFF 0.4 on Zarr v2)
with the tests' own writer (``tests/zarr_files.py``), which slices its source one chunk at a
time: the N³ array never exists in memory. For each N, each of these runs in a fresh Python
(so that its peak RSS, ``ru_maxrss``, is its own), on 1 and 2 threads (Dask's ``num_workers`` and
``set_kernel_threads``) and, for ``--cluster-sizes``, on a 2-process ``LocalCluster``:

- read: Dask reads and decompresses every chunk and keeps nothing;
- build: ``VolumeEVM.from_volume(read_volume(store), 300)``.

The targets: build ≤ 1.5 × read, and ns per voxel within 1.5× across sizes. For the smallest N
the chunked build is compared with ``from_array`` on the same resampled head in memory. For the
largest N the build (2 threads) is saved as a ``.vevm``, and fresh processes load it and time
``mesh()`` and 512² renders, shear-warp and ray casting, at ``level="auto"`` and ``"full"``;
first a fresh process checks that build against the store itself, slab by slab (the region's
mask at every voxel and its densities in order: equality with ``from_array`` without the
grid, which does not fit under the cap). Runs on N ≥ 1024 and the mesh and renders have
``VOLUMEEVM_MEMORY_LIMIT=6G``. Compiled kernels are used once on a small phantom before any
timing (in each cluster worker too), a render's on a subsample of the head. A step that fails
(a refused budget, a crash) is recorded with its message. Stores are deleted at the end unless
``--keep``.

Run: ``.venv/py313/bin/python bench/bench_scale.py [--sizes 256 512 1024] [--full] [--dir D]``.
"""

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import REPO, run_facts, write_json

DATA = REPO.parent / "shared" / "data"
THRESHOLD = 300.0
CHUNK = 128
CAP = "6G"
RENDER_SIZE = 512


class Resampled:
    """The head resampled by nearest neighbour to ``n``³, as a z, y, x array computed per slice
    (what ``tests.zarr_files.write_store`` needs of its source: shape, dtype, indexing)."""

    def __init__(self, head_xyz, n):
        self.head = head_xyz
        self.shape = (n, n, n)
        self.dtype = head_xyz.dtype
        self.index = [np.arange(n) * s // n for s in head_xyz.shape]  # x, y, z

    def __getitem__(self, key):
        ix, iy, iz = (i[k] for i, k in zip(self.index, reversed(key)))
        return np.ascontiguousarray(self.head[np.ix_(ix, iy, iz)].transpose(2, 1, 0))


def head():
    meta = json.loads((DATA / "ct_head_invesalius.json").read_text())
    return np.load(DATA / "ct_head_invesalius.npy"), meta["spacing_mm"]


def make_store(folder, n):
    """Write the N³ store; returns its path, seconds and bytes on disk."""
    from tests.zarr_files import write_store

    array, spacing = head()
    spacing = [s * m / n for s, m in zip(spacing, array.shape)]
    path = folder / f"head{n}.ome.zarr"
    start = time.perf_counter()
    write_store(path, [Resampled(array, n)], chunks=(CHUNK,) * 3, codec="blosc",
                spacing_zyx=tuple(reversed(spacing)))
    seconds = time.perf_counter() - start
    size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path, seconds, size


# ------------------------------------------------------------------ the steps, in fresh processes
def warm_kernels():
    """Use the compiled kernels once, in memory and chunk by chunk, and import numcodecs (loading
    them is not the step's time or memory). The chunked build runs on int16 densities in
    transposed chunks, as the stores' (z, y, x) chunks reach it, and with the same threshold:
    Numba compiles a kernel for each dtype it meets, so a float phantom alone would leave the
    int16 kernels to load or compile inside the timed build."""
    import dask.array as da
    import numcodecs  # noqa: F401

    from volumeevm_addon import Volume, VolumeEVM, phantoms

    box = phantoms.box((12, 12, 12), lo=(3, 3, 3), hi=(9, 9, 9), density=1000.0)
    VolumeEVM.from_volume(box, THRESHOLD).mesh()
    zyx = da.from_array(np.ascontiguousarray(box.array.T.astype(np.int16)), chunks=6)
    VolumeEVM.from_volume(Volume(zyx.T), THRESHOLD)


def warm_renderer(method, tf):
    """Use ``method``'s kernels once, on a subsample of the head of the same dtype, and the
    levels' (loading or compiling them is not the render's time)."""
    from volumeevm_addon import VolumeEVM, render

    array, _ = head()
    small = VolumeEVM.from_array(array[::8, ::8, ::4], THRESHOLD)
    small.level(2)
    camera, _ = view(small)
    render(small, camera, tf, method=method)


def peak_rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def read_all(volume):
    """Read and decompress every chunk; keep one zero per chunk."""
    return volume.array.map_blocks(lambda b: np.zeros((1, 1, 1), b.dtype),
                                   chunks=(1, 1, 1)).compute()


def run_step(spec):
    """One step (``spec``: step, store, mode, threads, ...) in this process; returns its facts."""
    import dask

    from volumeevm_addon import VolumeEVM, read_volume, render, set_kernel_threads

    step, facts = spec["step"], {}
    set_kernel_threads(spec.get("threads", 2))
    warm_kernels()
    client = cluster = None
    if spec.get("mode") == "cluster":
        from dask.distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
        client.run(warm_kernels)
    start = time.perf_counter()
    with dask.config.set(num_workers=spec.get("threads", 2)):
        if step == "read":
            read_all(read_volume(spec["store"]))
        elif step == "build":
            vevm = VolumeEVM.from_volume(read_volume(spec["store"]), THRESHOLD)
            facts["seconds"] = time.perf_counter() - start
            facts.update(voxel_count=vevm.voxel_count,
                         extreme_vertices=len(vevm.evm.vertices))
            if spec.get("compare"):
                facts["equals_from_array"] = equals_in_memory(vevm, spec["n"])
            if spec.get("save"):
                vevm.save(spec["save"], overwrite=False)
        elif step == "check":
            facts["equals_store"] = equals_store(VolumeEVM.load(spec["vevm"]),
                                                 read_volume(spec["store"]))
        else:
            vevm = VolumeEVM.load(spec["vevm"])
            start = time.perf_counter()
            if step == "mesh":
                mesh = vevm.mesh()
                facts["faces"] = len(mesh[1]) if isinstance(mesh, tuple) else str(type(mesh))
            else:
                camera, tf = view(vevm)
                warm_renderer(spec["method"], tf)
                start = time.perf_counter()
                rgba, _ = render(vevm, camera, tf, method=spec["method"], level=spec["level"])
                facts["covered_pixels"] = int((rgba[..., 3] > 0).sum())
    facts.setdefault("seconds", time.perf_counter() - start)
    facts["peak_rss_bytes"] = peak_rss()
    if client is not None:
        facts["worker_peak_rss_bytes"] = sorted(client.run(peak_rss).values())
        client.close()
        cluster.close()
    return facts


def equals_in_memory(vevm, n):
    """Whether ``vevm`` equals ``from_array`` on the resampled head in memory, field by field."""
    from volumeevm_addon import VolumeEVM

    array, _ = head()
    xyz = array[np.ix_(*(np.arange(n) * s // n for s in array.shape))]
    expected = VolumeEVM.from_array(xyz, THRESHOLD, spacing=vevm.spacing, origin=vevm.origin,
                                    orientation=vevm.orientation, units=vevm.units)
    same = np.array_equal(vevm.evm.vertices, expected.evm.vertices)
    same &= all(np.array_equal(vevm.table(a), expected.table(a)) for a in range(3))
    same &= all(getattr(vevm, f) == getattr(expected, f)
                for f in ("shape", "spacing", "origin", "threshold", "voxel_count"))
    return bool(same)


def equals_store(vevm, volume):
    """Whether ``vevm`` holds exactly the voxels ≥ 300 HU of the store and their densities, in
    order: its mask and table compared slab by slab (64 slices, never the grid) with the store
    read again: what equality with ``from_array`` means, at a size whose grid does not fit."""
    table, at, thickness = vevm.table(0), 0, 64
    nx, ny, nz = vevm.shape
    for x0 in range(0, nx, thickness):
        mask = vevm.evm.to_mask((min(thickness, nx - x0), ny, nz), offset=(x0, 0, 0))
        slab = np.asarray(volume.array[x0:x0 + len(mask)])
        if not np.array_equal(mask, slab >= THRESHOLD):
            return False
        values = slab[mask]
        if not np.array_equal(table[at:at + len(values)], values):
            return False
        at += len(values)
    return at == len(table) and vevm.threshold == THRESHOLD


def view(vevm):
    """The oblique orthographic camera of bench_dvr at 512², and the CT bone preset."""
    from bench_dvr import cameras

    from volumeevm_addon import TransferFunction, grid_to_world

    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    camera = cameras(vevm.shape, g, RENDER_SIZE, 30.0, 20.0, False)["ortho"]
    return camera, TransferFunction.preset("ct_bone")


def spawn(spec, capped):
    """Run ``spec`` in a fresh Python; its facts, or the failure's message."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("VOLUMEEVM_MEMORY_LIMIT", None)
    if capped:
        env["VOLUMEEVM_MEMORY_LIMIT"] = CAP
    done = subprocess.run([sys.executable, __file__, "--step", json.dumps(spec)], env=env,
                          capture_output=True, text=True, check=False)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    row = {**spec, "memory_limit": CAP if capped else None}
    if done.returncode != 0 or not lines:
        tail = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        return {**row, "failed": f"exit {done.returncode}: {tail}"}
    return {**row, **json.loads(lines[-1][len("RESULT "):])}


# -------------------------------------------------------------------------------------- main
def gib(b):
    return f"{b / 2 ** 30:.2f}"


def summary(runs, sizes):
    """Per size and mode: read, build, ratio, ns per voxel, peak RSS (the README's table)."""
    rows = []
    for n in sizes:
        for mode in ("threads1", "threads2", "cluster"):
            got = {r["step"]: r for r in runs if r["n"] == n and r["mode_name"] == mode}
            if "build" not in got:
                continue
            read, build = got.get("read", {}), got["build"]
            row = {"n": n, "mode": mode, "read_s": read.get("seconds"),
                   "build_s": build.get("seconds"), "failed": build.get("failed")}
            if row["read_s"] and row["build_s"]:
                row["build_over_read"] = row["build_s"] / row["read_s"]
                row["build_ns_per_voxel"] = row["build_s"] / n ** 3 * 1e9
            row["build_peak_rss_bytes"] = build.get("peak_rss_bytes")
            row["worker_peak_rss_bytes"] = build.get("worker_peak_rss_bytes")
            rows.append(row)
    return rows


def print_table(rows, spread):
    print(f"{'N':>5} {'mode':9} {'read s':>8} {'build s':>8} {'build/read':>10} "
          f"{'ns/voxel':>8} {'peak GiB':>8}")
    for r in rows:
        if r["failed"]:
            print(f"{r['n']:>5} {r['mode']:9} FAILED: {r['failed']}")
            continue
        print(f"{r['n']:>5} {r['mode']:9} {r['read_s']:8.2f} {r['build_s']:8.2f} "
              f"{r.get('build_over_read', float('nan')):10.2f} "
              f"{r.get('build_ns_per_voxel', float('nan')):8.2f} "
              f"{gib(r['build_peak_rss_bytes'] or 0):>8}")
    for mode, s in spread.items():
        print(f"ns per voxel, max / min across sizes, {mode}: {s:.2f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--step", help=argparse.SUPPRESS)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--full", action="store_true", help="add 2048³ (16 GiB of int16)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cluster-sizes", type=int, nargs="*", default=[512])
    parser.add_argument("--dir", type=Path, default=None, help="where the stores go")
    parser.add_argument("--keep", action="store_true", help="keep the stores")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    args = parser.parse_args()
    if args.step:
        print("RESULT " + json.dumps(run_step(json.loads(args.step))), flush=True)
        return
    sizes = sorted(set(args.sizes) | ({2048} if args.full else set()))
    folder = Path(tempfile.mkdtemp(prefix="bench_scale_", dir=args.dir))
    facts, stores, runs, largest = run_facts(), {}, [], {}
    try:
        for n in sizes:
            path, seconds, size = make_store(folder, n)
            stores[n] = {"write_s": seconds, "bytes_on_disk": size, "bytes_raw": 2 * n ** 3}
            print(f"[bench] {n}^3 store: {gib(size)} GiB on disk ({gib(2 * n ** 3)} raw), "
                  f"written in {seconds:.1f} s", flush=True)
            capped = n >= 1024
            modes = [(f"threads{t}", {"threads": t}) for t in args.threads]
            if n in args.cluster_sizes:
                modes.append(("cluster", {"threads": 1, "mode": "cluster"}))
            for name, mode in modes:
                for step in ("read", "build"):
                    spec = {"step": step, "store": str(path), "n": n, "mode_name": name, **mode}
                    # the field-by-field check needs the grid in memory: small sizes only
                    if step == "build" and n == sizes[0] <= 512 and name == "threads2":
                        spec["compare"] = True
                    if step == "build" and n == sizes[-1] and name == f"threads{args.threads[-1]}":
                        spec["save"] = str(folder / f"head{n}.vevm")
                    runs.append(spawn(spec, capped))
                    r = runs[-1]
                    print(f"[bench] {n}^3 {name:8s} {step:5s} "
                          + (f"FAILED {r['failed']}" if "failed" in r else
                             f"{r['seconds']:8.2f} s, peak {gib(r['peak_rss_bytes'])} GiB"
                             + (f", {r['voxel_count']} voxels" if "voxel_count" in r else "")
                             + (f", equals from_array: {r['equals_from_array']}"
                                if "equals_from_array" in r else "")), flush=True)
            if n != sizes[-1] and not args.keep:
                shutil.rmtree(path)
        saved = folder / f"head{sizes[-1]}.vevm"
        if saved.exists():
            steps = [("check", {"store": str(folder / f"head{sizes[-1]}.ome.zarr")}),
                     ("mesh", {})] + [("render", {"method": method, "level": level})
                                      for method in ("shear_warp", "raycast")
                                      for level in ("auto", "full")]
            for step, extra in steps:
                spec = {"step": step, "vevm": str(saved), "n": sizes[-1], "mode_name": "threads2",
                        "threads": 2, **extra}
                r = spawn(spec, True)
                name = step if step == "check" else " ".join([step, *extra.values()])
                largest[name] = r
                print(f"[bench] {sizes[-1]}^3 {name}: "
                      + (f"FAILED {r['failed']}" if "failed" in r else
                         f"{r['seconds']:.2f} s, peak {gib(r['peak_rss_bytes'])} GiB"
                         + (f", equals the store: {r['equals_store']}"
                            if "equals_store" in r else "")),
                      flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    rows = summary(runs, sizes)
    spread = {}
    for mode in ("threads1", "threads2"):
        ns = [r["build_ns_per_voxel"] for r in rows if r["mode"] == mode
              and r.get("build_ns_per_voxel")]
        if len(ns) > 1:
            spread[mode] = max(ns) / min(ns)
    print_table(rows, spread)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "scale.json", {
        **facts, "threshold_hu": THRESHOLD, "dtype": "int16", "chunks": [CHUNK] * 3,
        "codec": "blosc zstd 3", "sizes": sizes, "stores": stores, "summary": rows,
        "ns_per_voxel_spread": spread, "largest": largest, "runs": runs})


if __name__ == "__main__":
    main()
