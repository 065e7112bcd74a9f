"""Memory estimates against measured peaks: import, build, mesh and render (issue 9, section 4).

For the CT head of ../shared/data (read with ``read_volume``, its JSON sidecar giving the
spacing) and the same head upsampled to 512³ (nearest neighbour, int16, written as ``.npy``
with a sidecar in a temporary folder and read back), each step runs under ``tracemalloc``:

- import: ``read_volume``;
- build: ``VolumeEVM.from_volume`` at 300 HU;
- mesh: ``vevm.mesh()``;
- render: every method at 256² and 512², default quality, the orthographic oblique view of
  ``bench_dvr``, each method on a VolumeEVM of its own (the first size builds the method's
  cached tables: "cold"; the second reuses them: "warm", and its estimate leaves them out).

Two questions per step, answered without trusting the estimates' own code:

1. **What did VolumeEVM estimate?** Every call of ``check_memory`` during the step is recorded
   (the largest ``needed`` is the step's estimate; none means the step checks nothing).
2. **Does a budget just below the measured peak refuse the step?** The step runs again with
   ``VOLUMEEVM_MEMORY_LIMIT`` at 95 % of its measured peak: a conservative estimate refuses
   (``refused_below_peak``), an underestimate lets it run.

The whole run keeps a budget (``--budget``, default 8G) so that a step whose estimate exceeds
it is refused, not run: the row then says so, with the estimate (the reference on 512³ needs
about 8 GiB). Prints a table and writes ``memory.json`` and ``memory.md`` to ``--out``.

Usage: ``python bench/bench_memory.py --out bench/results``
"""

import argparse
import importlib
import json
import os
import pkgutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import volumeevm_addon  # noqa: E402
from bench._common import run_facts, write_json  # noqa: E402
from bench.bench_dvr import cameras  # noqa: E402
from volumeevm_addon import (  # noqa: E402
    LIMIT_VARIABLE,
    METHODS,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    check_memory,
    grid_to_world,
    phantoms,
    read_volume,
    render,
    write_atomically,
)

DATA = REPO.parent / "shared" / "data"
THRESHOLD = 300.0
SIZES = (256, 512)
BELOW_PEAK = 0.95


class Estimates:
    """Records every ``check_memory`` call: each module of the package (all imported first)
    that imported it gets a recorder that notes ``(needed, what)`` and then checks as before."""

    def __init__(self):
        self.calls = []
        original = check_memory
        for info in pkgutil.walk_packages(volumeevm_addon.__path__, "volumeevm_addon."):
            importlib.import_module(info.name)

        def recorder(needed, what, *, source, advice=""):
            self.calls.append((int(needed), f"{source}: {what}"))
            return original(needed, what, source=source, advice=advice)

        for module in list(sys.modules.values()):
            if (getattr(module, "__name__", "").startswith("volumeevm_addon")
                    and getattr(module, "check_memory", None) is original):
                module.check_memory = recorder

    def largest(self):
        """``(needed, what)`` of the largest estimate since the last call, or ``(None, "")``."""
        calls, self.calls = self.calls, []
        return max(calls) if calls else (None, "")


def measure(step, estimates, again=None):
    """Peak traced bytes of ``step()``, its result, the largest estimate, and whether a budget
    at 95 % of the peak refuses ``again()`` (the step in the state it ran in: a cold render
    again on a VolumeEVM without cached tables; ``step`` by default; None when the step
    itself was refused)."""
    estimates.largest()
    tracemalloc.start()
    start = time.perf_counter()
    try:
        result = step()
        refused = None
    except VolumeEVMError as error:
        result, refused = None, str(error)
    seconds = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    needed, what = estimates.largest()
    row = {"peak": peak, "estimate": needed, "estimate_of": what, "seconds": round(seconds, 2),
           "refused": refused, "refused_below_peak": None}
    if refused is None:
        budget = os.environ.get(LIMIT_VARIABLE)
        os.environ[LIMIT_VARIABLE] = str(int(BELOW_PEAK * peak))
        try:
            (again or step)()
            row["refused_below_peak"] = False
        except VolumeEVMError:
            row["refused_below_peak"] = True
        finally:
            os.environ[LIMIT_VARIABLE] = budget
        estimates.largest()
    return row, result


def upsampled_head(folder):
    """The CT head upsampled to 512³ (nearest neighbour, same physical size), written as
    ``head512.npy`` with its sidecar in ``folder``; returns the path."""
    meta = json.loads((DATA / "ct_head_invesalius.json").read_text())
    head = np.load(DATA / "ct_head_invesalius.npy")
    index = [(np.arange(512) * n) // 512 for n in head.shape]
    big = head[np.ix_(*index)].astype(np.int16)
    spacing = [s * n / 512 for s, n in zip(meta["spacing_mm"], head.shape)]
    path = Path(folder) / "head512.npy"
    np.save(path, big)
    sidecar = {"shape": list(big.shape), "dtype": "int16", "axis_order": "xyz",
               "spacing_mm": spacing, "spacing_known": True, "units": "Hounsfield units"}
    path.with_suffix(".json").write_text(json.dumps(sidecar))
    return path


def load_kernels():
    """Use every compiled kernel once on a small volume before measuring: their first use in a
    process (importing Numba, loading or compiling the kernels) allocates some 40 MiB once,
    which is not the memory of the step that happens to come first."""
    vevm = VolumeEVM.from_volume(phantoms.box((12, 12, 12), lo=(3, 3, 3), hi=(9, 9, 9)), 0.5)
    vevm.mesh()
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    cam = cameras(vevm.shape, g, 16, 30.0, 20.0, False)["ortho"]
    for method in METHODS:
        render(vevm, cam, TransferFunction.preset("ct_bone", data_range=(0.0, 1.0)),
               method=method)


def run_volume(name, path, estimates, rows):
    """Every step on one volume file; appends a row per step."""
    def add(step, row, **extra):
        rows.append({"volume": name, "step": step, **extra, **row})
        r = rows[-1]
        print(f"[bench] {name:8s} {step:28s} peak {mib(r['peak']):>9s} estimate "
              f"{mib(r['estimate']):>9s} refused below peak: {r['refused_below_peak']}"
              f"{'  REFUSED: ' + r['refused'] if r['refused'] else ''}", flush=True)

    row, volume = measure(lambda: read_volume(path), estimates)
    add("import (read_volume)", row)
    row, vevm = measure(lambda: VolumeEVM.from_volume(volume, THRESHOLD), estimates)
    add(f"build ({THRESHOLD:g} HU)", row, voxels=int(np.prod(volume.shape)))
    row, _ = measure(vevm.mesh, estimates)
    add("mesh", row, extreme_vertices=len(vevm.evm.vertices))
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    tf = TransferFunction.preset("ct_bone")
    for method in METHODS:
        vevm = VolumeEVM.from_volume(volume, THRESHOLD)  # no tables cached by another method
        for size in SIZES:
            cold = size == SIZES[0]
            again = VolumeEVM.from_volume(volume, THRESHOLD) if cold else vevm
            cam = cameras(vevm.shape, g, size, 30.0, 20.0, False)["ortho"]
            row, _ = measure(lambda: render(vevm, cam, tf, method=method), estimates,
                             lambda: render(again, cam, tf, method=method))
            add(f"render {method} {size}²", row, method=method, size=size,
                cache="cold" if cold else "warm")


def mib(count):
    return "-" if count is None else f"{count / 2**20:.1f} MiB"


def markdown(rows, facts):
    lines = [
        "# Memory: estimate against measured peak (tracemalloc)", "",
        f"Commit {facts['commit'][:10]}, Python {facts['python']}, NumPy {facts['numpy']}, "
        f"{facts['date_utc']}; budget for the run {facts['budget']}. Estimate: the largest "
        "`check_memory` of the step (render estimates count only the tables the render would "
        "still build: a warm render's are cached). "
        f"'Refused below peak': a budget of {BELOW_PEAK:.0%} of the measured peak refuses the "
        "step (the estimate is conservative).", "",
        "| volume | step | cache | measured peak | estimate | estimate / peak | refused below "
        "peak | seconds | note |",
        "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = (f"{r['estimate'] / r['peak']:.2f}" if r["estimate"] and r["peak"]
                 and not r["refused"] else "-")
        note = f"refused by the run's budget: {r['refused']}" if r["refused"] else ""
        lines.append(f"| {r['volume']} | {r['step']} | {r.get('cache', '')} | "
                     f"{mib(r['peak']) if not r['refused'] else '-'} | {mib(r['estimate'])} | "
                     f"{ratio} | {r['refused_below_peak']} | {r['seconds']} | {note} |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--budget", default="8G", help="VOLUMEEVM_MEMORY_LIMIT for the run")
    parser.add_argument("--skip-512", action="store_true", help="only the CT head")
    args = parser.parse_args()
    os.environ[LIMIT_VARIABLE] = args.budget
    facts = {**run_facts(), "budget": args.budget}
    estimates = Estimates()
    rows = []
    load_kernels()
    run_volume("ct_head", DATA / "ct_head_invesalius.npy", estimates, rows)
    if not args.skip_512:
        with tempfile.TemporaryDirectory() as folder:
            run_volume("512³", upsampled_head(folder), estimates, rows)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "memory.json", {"facts": facts, "rows": rows})
    text = markdown(rows, facts)
    write_atomically(args.out / "memory.md", lambda temporary: temporary.write_text(text),
                     overwrite=True)
    print(text)


if __name__ == "__main__":
    main()
