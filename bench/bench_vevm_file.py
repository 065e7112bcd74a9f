"""A .vevm file larger than 4 GiB (Zip64): saved and loaded, with time and peak memory.

A box region of ``--size``³ voxels (default 1700³: 4.9 GB of uint8 densities, a table past the
32-bit ZIP limits) is built from its EVM and a table with a known pattern, saved, and loaded
again in a fresh process, where every check of ``VolumeEVM.load`` runs as for any file (ZIP
directory, ``.npy`` headers, sizes against the free memory, SHA-256 of both arrays, the
region). Each step runs in its own process so its peak RSS (``ru_maxrss``) is its own: the
target is a load that holds one table, not two (peak ≤ 1.15 × the table), and a save that
streams the table into the file without a copy. The file is removed at the end.

Run: ``.venv/py313/bin/python bench/bench_vevm_file.py [--size N] [--dir FOLDER]``.
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import REPO, run_facts, write_json

STEP = r"""
import json, resource, sys, time
import numpy as np
sys.path.insert(0, {repo!r})
from volumeevm_addon import VolumeEVM
from volumeevm_addon.model import box_evm

size, path, step = {size}, {path!r}, {step!r}
count = size ** 3
start = time.perf_counter()
if step == "save":
    table = np.full(count, 7, np.uint8)  # every page touched: the table really in memory
    table[::4096] = np.arange(len(table[::4096])) % 251  # a pattern the load checks
    made = time.perf_counter()
    vevm = VolumeEVM(box_evm((0, 0, 0), (size,) * 3, (size,) * 3), table, shape=(size,) * 3)
    vevm.save(path, overwrite=False)
    facts = {{"make_table_s": made - start}}
else:
    vevm = VolumeEVM.load(path)
    table = vevm.table(0)
    ok = (vevm.voxel_count == count and table.dtype == np.uint8
          and np.array_equal(table[::4096], np.arange(len(table[::4096])) % 251))
    facts = {{"checked_equal": bool(ok)}}
facts["seconds"] = time.perf_counter() - start
facts["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print("RESULT " + json.dumps(facts), flush=True)
"""


def step(name, size, path):
    """Run one step in a fresh Python; returns its facts."""
    code = STEP.format(repo=str(REPO), size=size, path=str(path), step=name)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        raise SystemExit(f"{name} failed:\n{done.stdout}\n{done.stderr}")
    return json.loads(lines[-1][len("RESULT "):])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1700, help="edge of the box region, voxels")
    parser.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()))
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    args = parser.parse_args()
    table_bytes = args.size ** 3
    path = args.dir / f"bench_vevm_{os.getpid()}.vevm"
    facts = run_facts()
    try:
        save = step("save", args.size, path)
        file_bytes = path.stat().st_size
        load = step("load", args.size, path)
    finally:
        path.unlink(missing_ok=True)
    result = {
        **facts,
        "size": args.size,
        "table_bytes": table_bytes,
        "file_bytes": file_bytes,
        "save": save,
        "load": load,
        "load_peak_over_table": load["peak_rss_bytes"] / table_bytes,
        "save_peak_over_table": save["peak_rss_bytes"] / table_bytes,
        "self_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
    }
    print(f"[bench] {args.size}^3 uint8: table {table_bytes / 2**30:.2f} GiB, file "
          f"{file_bytes / 2**30:.2f} GiB; save {save['seconds']:.1f} s (peak "
          f"{result['save_peak_over_table']:.2f} x table), load {load['seconds']:.1f} s (peak "
          f"{result['load_peak_over_table']:.2f} x table), loaded equal: {load['checked_equal']}")
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "vevm_file.json", result)


if __name__ == "__main__":
    main()
