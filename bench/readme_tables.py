"""The README's benchmark tables, generated from ``bench/results/`` (never copied by hand).

Each table sits in README.md between marker comments that say what goes there::

    <!-- bench:evm_core -->                       ... <!-- /bench:evm_core -->
    <!-- bench:speed_accuracy:ct_head:ortho -->   ... <!-- /bench:speed_accuracy:ct_head:ortho -->
    <!-- bench:dvr_targets -->                    ... <!-- /bench:dvr_targets -->

``bench:evm_core`` is built from ``bench_evm.json``; ``bench:speed_accuracy:<dataset>:<view>``
is the time-to-ε table of that dataset and view, built from ``speed_accuracy.csv`` (the runs)
and ``bench_dvr.json`` (the scene and the run's facts) by the same code as
``speed_accuracy.md``; ``bench:dvr_targets`` from ``bench_dvr.json``'s target checks. Each
block names the commit and the machine of its results. ``make bench`` runs this script last;
``--check`` rewrites nothing and exits with 1 when the README differs from what the results
give (``tests/test_readme_tables.py``), so the README cannot drift.

Usage: ``python bench/readme_tables.py [--check] [--readme README.md] [--results bench/results]``
"""

import argparse
import json
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.bench_dvr import groups, read_csv, time_table  # noqa: E402
from volumeevm_addon.system import write_atomically  # noqa: E402

BLOCK = re.compile(r"(<!-- bench:(?P<name>[\w:]+) -->\n)(?P<body>.*?)(<!-- /bench:(?P=name) -->)",
                   re.DOTALL)
VIEWS = {"ortho": "orthographic", "persp": "perspective"}


def _facts(result, timing):
    """The line naming where a result comes from: commit, machine, timing."""
    changed = len(result["modified_files_at_start"])
    return (f"Measured at commit {result['commit'][:7]}"
            + (f" with {changed} files changed" if changed else "")
            + f" on {result['machine']} ({result['date_utc'][:10]}; {timing}).")


def _times(ratio):
    """A speed ratio as the README words it: "1.1× faster", or "1.0×" when not faster."""
    text = f"{ratio:.1f}×"
    return f"{text} faster" if float(f"{ratio:.1f}") > 1.0 else text


def _ms(seconds):
    """A frame time in milliseconds, with a decimal below 10 ms (VolPack's small frames)."""
    return f"{seconds * 1000:.1f} ms" if seconds < 0.01 else f"{seconds * 1000:.0f} ms"


def _target(measured, target, at_least, where=""):
    """The target column: the bound and whether the measured value meets it."""
    met = measured >= target if at_least else measured <= target
    return (f"{'≥' if at_least else '≤'} {target:g}{'×' if at_least else ''}{where} — "
            + ("met" if met else "**not met**"))


def evm_core(results):
    """The EVM core table (``bench_evm.json``): one column per CT threshold and MRI, and the
    kernels' first use."""
    result = json.loads((results / "bench_evm.json").read_text())
    rows, mris = result["rows"], result["mri_rows"]
    targets, measured, kernels = result["targets"], result["measured"], result["kernels"]
    surfaces = rows + mris
    speed, vtk = ("extract_mesh_speedup_vs_marching_cubes",
                  "extract_mesh_speedup_vs_vtk_flying_edges")

    def line(label, cells, target=""):
        cells = list(cells) + [""] * (len(surfaces) - len(cells))  # CT-only rows
        return "|" + "|".join(f" {c} " if c else " " for c in (label, *cells, target)) + "|"

    head = ([f"CT {r['case']} ({r['threshold_hu']:g} HU)".replace("-", "−") for r in rows]
            + [f"{r['case']} (≥ {r['threshold_hu']:g})" for r in mris])
    return [
        _facts(result, result["timing"] + f"; {rows[0]['threads']} threads"), "",
        line("", head, "target"),
        "|---" * (len(surfaces) + 2) + "|",
        line("voxels / extreme vertices",
             [f"{r['voxels']:,} / {r['extreme_vertices']:,}" for r in surfaces]),
        line("EVM extraction + closed mesh, 1 thread / all",
             [f"{r['evm_extract_mesh_1thread_s'] * 1000:.0f} / {r['evm_extract_mesh_s'] * 1000:.0f}"
              " ms" for r in surfaces]),
        line("… vs scikit-image `marching_cubes` (one thread)",
             [_times(r[speed]) for r in surfaces],
             _target(measured[speed], targets[speed], True)),
        line("… vs VTK flying edges (same threads)", [f"{r[vtk]:.2f}×" for r in surfaces],
             _target(measured[vtk], targets[vtk], True)),
        line("mesh polygons per unit voxel face",
             [f"{r['mesh_faces_per_unit_face']:.3f}" for r in surfaces],
             _target(measured["mesh_faces_per_unit_face_bone"],
                     targets["mesh_faces_per_unit_face_bone"], False, " (bone)")),
        line("cut by a box / a sphere: sweep vs dense Boolean + re-extraction",
             [f"{r['cut_box_speedup_vs_dense']:.1f}× / {r['cut_sphere_speedup_vs_dense']:.1f}×"
              for r in rows]),
        line("VolumeEVM bytes vs the dense array", [f"{r['bytes_vs_dense']:.3f}" for r in rows],
             _target(measured["bytes_vs_dense_bone"], targets["bytes_vs_dense_bone"], False,
                     " (bone)")),
        "",
        f"Kernels' first use ({kernels['case']}, a fresh process): "
        f"{kernels['cold_first_call_s']:.1f} s with an empty kernel cache (compiling), "
        f"{kernels['warm_first_call_s'] * 1000:.0f} ms with it filled (loading), against "
        f"{kernels['compiled_call_s'] * 1000:.0f} ms once loaded; importing the package takes "
        f"{kernels['package_import_s'] * 1000:.0f} ms.",
    ]


def speed_accuracy(results, dataset, view):
    """The time-to-ε table of one dataset and view (``speed_accuracy.csv``), with its scene."""
    result = json.loads((results / "bench_dvr.json").read_text())
    info = result["datasets"][dataset]
    by = groups(read_csv(results / "speed_accuracy.csv"))[(dataset, view)]
    shape = "×".join(str(n) for n in info["shape"])
    width, height = info["views"][view]["size"]
    size = f"{width}²" if width == height else f"{width}×{height}"
    return [f"**{dataset}** — {info['panel']}, {shape} → {size}, {VIEWS.get(view, view)}. "
            + _facts(result, result["timing"]), "", *time_table(by)]


def dvr_targets(results):
    """Issue 11's two DVR targets per dataset and view (``bench_dvr.json``), in one table."""
    result = json.loads((results / "bench_dvr.json").read_text())
    targets = result["targets"]
    vtk_goal = targets["speedup_vs_vtk_at_vtk_error_at_least"]
    volpack_goal = targets["shear_warp_time_over_volpack_at_volpack_error_at_most"]
    lines = [_facts(result, result["timing"]), "",
             f"| dataset (view) | VTK's error (its time) | our fastest there | vs VTK "
             f"(≥ {vtk_goal:g}× faster) | VolPack's error (its time) | shear-warp there | "
             f"vs VolPack (≤ "
             f"{volpack_goal:g}× its time) |", "|---" * 7 + "|"]
    for c in result["target_results"]:
        cells = [f"{c['dataset']} ({c['view']})"]
        if "vtk_rmse" in c:
            best = c.get("best_at_vtk_error")
            cells += [f"{c['vtk_rmse']:.4f} ({_ms(c['vtk_s'])})", best or "none",
                      f"{c['speedup_vs_vtk']:.2f}× — {'met' if c['vtk_target_met'] else 'not met'}"
                      if best else "not met"]
        else:
            cells += ["", "", ""]
        if "volpack_rmse" in c:
            best = c.get("shear_warp_at_volpack_error")
            cells += [f"{c['volpack_rmse']:.4f} ({_ms(c['volpack_s'])})", best or "none",
                      f"{c['shear_warp_time_over_volpack']:.1f}× — "
                      f"{'met' if c['volpack_target_met'] else 'not met'}" if best else "not met"]
        else:
            cells += ["—", "", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def shading(results):
    """Shading before and after the 3x3x3 Sobel and the fade (``shading_before.json``,
    ``shading_after.json`` of ``bench/shading_pictures.py``): each method's error against the
    reference with the same gradients, and its frame times."""
    before, after = (json.loads((results / f"shading_{label}.json").read_text())
                     for label in ("before", "after"))
    lines = [f"Before: commit {before['facts']['errors']['commit'][:7]}. After: "
             + _facts(after["facts"]["errors"], "errors"),
             "", "| method | central differences: mean, p99, RMSE | 3×3×3 Sobel + fade |",
             "|---" * 3 + "|"]
    for method, old in before["errors"].items():
        new = after["errors"][method]
        lines.append(f"| {method} | " + " | ".join(
            f"{e['mean']:.4f}, {e['p99']:.3f}, {e['rmse']:.4f}" for e in (old, new)) + " |")
    facts = after["facts"]["timings"]
    lines += ["", f"Frame times of a shaded 256×256 view of the full CT head on {facts['machine']}"
              f" (shared; load {facts['load_average_at_start']} at the start), before → after:",
              "", "| method, threads | first frame (gradients made) | a later frame (best of 3) |",
              "|---" * 3 + "|"]
    for key, old in before["timings"].items():
        new = after["timings"][key]
        lines.append(f"| {key.replace(' 1 threads', ' 1 thread')} | "
                     f"{_ms(old['first_s'])} → {_ms(new['first_s'])} | "
                     f"{_ms(old['later_s'])} → {_ms(new['later_s'])} |")
    return lines


def block(name, results):
    """The Markdown lines of the block ``name`` (the marker's name)."""
    kind, *args = name.split(":")
    makers = {"evm_core": evm_core, "speed_accuracy": speed_accuracy, "dvr_targets": dvr_targets,
              "shading": shading}
    if kind not in makers:
        raise SystemExit(f"README.md: unknown benchmark block <!-- bench:{name} -->")
    return makers[kind](results, *args)


def render_readme(text, results):
    """``text`` with every benchmark block replaced by what ``results`` give."""
    return BLOCK.sub(lambda m: m.group(1) + "\n".join(block(m.group("name"), results)) + "\n"
                     + m.group(4), text)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--readme", type=Path, default=REPO / "README.md")
    parser.add_argument("--results", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--check", action="store_true",
                        help="change nothing; exit 1 if the README differs from the results")
    args = parser.parse_args(argv)
    text = args.readme.read_text()
    if not BLOCK.search(text):
        raise SystemExit(f"{args.readme}: no <!-- bench:... --> block to fill")
    new = render_readme(text, args.results)
    if args.check:
        if new != text:
            print(f"{args.readme}: benchmark tables differ from {args.results}; "
                  "run python bench/readme_tables.py", file=sys.stderr)
            return 1
        return 0
    if new != text:
        write_atomically(args.readme, lambda temporary: temporary.write_text(new), overwrite=True)
        print(f"wrote {args.readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
