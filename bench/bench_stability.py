"""The stability suite at full size: where each method fails, measured (issue 5).

The tests ``tests/test_stability_*.py`` run these sweeps at CI size with bounds; this bench runs
them larger (images ``--size``², finer angle steps) and writes what it measures, so a change of
method can be judged on the full curves. Design: ``../shared/design/notes/dvr_evaluation.md``
§3.2 (measures) and §7.8 (the tests). Every frame of every sweep is compared with the dense
reference renderer's image of the same frame; the measures are :mod:`volumeevm_addon.metrics`.

- S1 rotation about x from 0° to 90° (0.25° steps from 40° to 50°): per-frame RMSE, popping
  index and bias jump at 45°, largest temporal error, on Marschner–Lobb 41³ with a pulse.
- S2 rotation about the (1, 1, 1) diagonal through 120° (the slice family changes between all
  three axes every 60°): same measures.
- S3 zoom 0.25 to 8 pixels per voxel: RMSE per zoom, at the full level and at ``level="auto"``,
  against the reference supersampled 4×4 per pixel (a point-sampled reference aliases at
  minification, and would reward a method for aliasing the same way).
- S4 ray step 2 to 0.25 voxel with and without jitter: RMSE and the spectral peak of the error
  image (banding).
- S5 pulse width 0.1 to 0.01 of the range with and without pre-integration (step 1 voxel): RMSE
  (the reference steps voxel/64 here).
- S6 one-voxel plate rotated 0° to 90°: largest relative deviation of integrated alpha from the
  reference's, and drop-out pixels (reference alpha > 0.05, method alpha 0).
- S8 early-termination threshold 0.9 to 0.999 on the CT head: frame time and the largest
  deviation from the same method without termination (the bound is ``1 - threshold``).

S7 (anisotropic spacing), S9 (robustness) and S10 (VolumeEVM against dense) have no sweep to
chart; they are tests only. Outputs in ``--out``: ``stability.md`` (tables), ``stability.json``
and ``stability_<test>.png`` (curves; needs matplotlib).

Usage: ``python bench/bench_stability.py [--out bench/results] [--size 128] [--tests s1,s2,...]``
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._common import accepts, run_facts, write_json  # noqa: E402
from volumeevm_addon import BLENDER_UNITS_PER_MM as BU  # noqa: E402
from volumeevm_addon import (  # noqa: E402
    Camera,
    TransferFunction,
    VolumeEVM,
    grid_to_world,
    phantoms,
    render,
    write_atomically,
)
from volumeevm_addon.metrics import (  # noqa: E402
    bias_jump,
    popping_index,
    rmse,
    spectral_peak,
    temporal_errors,
)

DATA = REPO.parent / "shared" / "data"
# Each method at its default and at the settings meant to fix its failure modes.
VARIANTS = {
    "shear_warp": {},
    "shear_warp 2 slices": {"slices_per_voxel": 2},
    "shear_warp post 2 slices": {"slices_per_voxel": 2, "classification": "post"},
    "splat": {},
    "splat 3 sub-slabs": {"substeps": 3},
    "raycast": {},
    "raycast jitter": {"jitter": True},
    "raycast preintegrated": {"preintegrate": True},
}


def variants():
    """The variants this version of the renderers accepts: name -> (method, options)."""
    out = {}
    for name, options in VARIANTS.items():
        method = name.split()[0]
        if accepts(method, options):
            out[name] = (method, options)
    return out


def pulse(width, alpha=0.3, centre=0.5):
    """Opacity ``alpha`` per mm at ``centre`` falling to 0 at ``centre ± width / 2``."""
    return TransferFunction([(0.0, 1, 1, 1, 0), (centre - width / 2, 1, 1, 1, 0),
                             (centre, 1, 0.8, 0.6, alpha), (centre + width / 2, 1, 1, 1, 0),
                             (1.0, 1, 1, 1, 0)])


def orbit(vevm, direction, up, size, zoom=None):
    """Orthographic ``size``² camera looking at the grid's centre from ``direction``, framing
    the grid (or at ``zoom`` pixels per voxel)."""
    g = grid_to_world(vevm.spacing, vevm.origin)
    c = g[:3, 3] + g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0)
    extent = float(np.linalg.norm(np.array(vevm.shape) * vevm.spacing)) * BU
    scale = 1.02 * extent if zoom is None else size * min(vevm.spacing) * BU / zoom
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return Camera.look_at(c + d * extent, c, up, ortho_scale=scale, resolution_x=size,
                          resolution_y=size, clip_start=1e-4)


def frames(vevm, tf, cams):
    """Reference and every variant's images for each camera: {name: (N, H, W, 4)}."""
    table = variants()
    out = {"reference": [], **{n: [] for n in table}}
    for cam in cams:
        out["reference"].append(render(vevm, cam, tf, method="reference")[0])
        for n, (method, options) in table.items():
            out[n].append(render(vevm, cam, tf, method=method, **options)[0])
    return {k: np.array(v) for k, v in out.items()}


def sweep_measures(images, angles, at):
    """Per-variant measures of an orbit against the reference's frames (popping index and
    bias jump within 5° of the switch at ``at``)."""
    ref = images["reference"]
    angles = np.asarray(angles)
    near = np.abs(angles - at) <= 5.0
    rows = {}
    for name, ims in images.items():
        if name == "reference":
            continue
        curve = [rmse(a, b) for a, b in zip(ims, ref)]
        rows[name] = {
            "rmse_mean": float(np.mean(curve)),
            "rmse_max": float(max(curve)),
            "popping_index": popping_index(ims[near], ref[near]),
            "bias_jump": bias_jump(angles[near], ims[near], ref[near], at=at),
            "temporal_error_max": float(temporal_errors(ims, ref).max()),
            "curve": curve,
        }
    return rows


def ml():
    return VolumeEVM.from_volume(phantoms.marschner_lobb(41), -1.0)


# ----------------------------------------------------------------------------- the sweeps
def s1(args):
    vevm = ml()
    angles = np.unique(np.concatenate([np.arange(0, 40, 2.0), np.arange(40, 50.01, 0.25),
                                       np.arange(52, 90.01, 2.0)]))
    cams = [orbit(vevm, (0.0, -np.cos(np.radians(a)), np.sin(np.radians(a))), (1, 0, 0),
                  args.size) for a in angles]
    images = frames(vevm, pulse(0.1), cams)
    return {"angles": angles.tolist(), "rows": sweep_measures(images, angles, 45.0)}


def s2(args):
    vevm = ml()
    axis = np.ones(3) / np.sqrt(3)
    start = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    angles = np.arange(0, 120.01, 1.0)
    dirs = [np.cos(np.radians(a)) * start + np.sin(np.radians(a)) * np.cross(axis, start)
            for a in angles]
    cams = [orbit(vevm, d, axis, args.size) for d in dirs]
    images = frames(vevm, pulse(0.1), cams)
    # The principal axis of a direction in this plane changes every 60°, starting at 30°.
    return {"angles": angles.tolist(), "rows": sweep_measures(images, angles, 90.0)}


def s3(args):
    vevm = ml()
    tf = pulse(0.1)
    zooms = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
    n = args.size // 2
    refs = [render(vevm, orbit(vevm, (0.3, -1.0, 0.5), (0, 0, 1), 4 * n, zoom=4 * z), tf,
                   method="reference")[0].reshape(n, 4, n, 4, 4).mean(axis=(1, 3))
            for z in zooms]
    rows = {}
    for name, (method, options) in variants().items():
        if name not in ("shear_warp", "splat", "raycast"):  # the defaults
            continue
        for level in ("full", "auto"):
            curve = []
            for z, ref in zip(zooms, refs):
                cam = orbit(vevm, (0.3, -1.0, 0.5), (0, 0, 1), n, zoom=z)
                img = render(vevm, cam, tf, method=method, level=level, **options)[0]
                curve.append(rmse(img, ref))
            rows[f"{name} level={level}"] = {"curve": curve, "rmse_max": max(curve)}
    return {"zooms": list(zooms), "rows": rows}


def s4(args):
    vevm = ml()
    tf = pulse(0.1)
    cam = orbit(vevm, (0.3, -1.0, 0.5), (0, 0, 1), args.size)
    ref = render(vevm, cam, tf, method="reference")[0]
    steps = (2.0, 1.0, 0.5, 0.25)
    rows = {}
    for jitter in (False, True):
        if jitter and not accepts("raycast", {"jitter": True}):
            continue
        errors, peaks = [], []
        for s in steps:
            img = render(vevm, cam, tf, method="raycast", step_mm=s,
                         **({"jitter": True} if jitter else {}))[0]
            errors.append(rmse(img, ref))
            peaks.append(spectral_peak((img - ref)[..., 3]))
        rows[f"raycast{' jitter' if jitter else ''}"] = {"curve": errors, "spectral_peak": peaks}
    return {"steps_voxels": list(steps), "rows": rows}


def s5(args):
    vevm = ml()
    cam = orbit(vevm, (0.3, -1.0, 0.5), (0, 0, 1), args.size // 2)
    widths = (0.1, 0.05, 0.02, 0.01)
    refs = {w: render(vevm, cam, pulse(w), method="reference", step_mm=1.0 / 64)[0]
            for w in widths}
    rows = {}
    for pre in (False, True):
        if pre and not accepts("raycast", {"preintegrate": True}):
            continue
        for step in (1.0, 0.5):
            curve = [rmse(render(vevm, cam, pulse(w), method="raycast", step_mm=step,
                                 **({"preintegrate": True} if pre else {}))[0], refs[w])
                     for w in widths]
            rows[f"raycast step {step}{' preintegrated' if pre else ''}"] = {"curve": curve}
    return {"widths": list(widths), "rows": rows}


def s6(args):
    shape = (48, 48, 48)
    vevm = VolumeEVM.from_volume(phantoms.thin_plate(shape, (0.0, 0.0, 1.0), 1.0), 0.01)
    tf = TransferFunction([(0.0, 0.9, 0.7, 0.5, 0.0), (1.0, 0.9, 0.7, 0.5, 0.9)])
    angles = np.arange(0, 90.01, 5.0)
    cams = [orbit(vevm, (0.0, -np.sin(np.radians(a)), np.cos(np.radians(a))), (1, 0, 0),
                  args.size) for a in angles]
    images = frames(vevm, tf, cams)
    ref = images["reference"]
    ref_alpha = ref[..., 3].sum(axis=(1, 2))
    rows = {}
    for name, ims in images.items():
        if name == "reference":
            continue
        dev = np.abs(ims[..., 3].sum(axis=(1, 2)) - ref_alpha) / np.maximum(ref_alpha, 1e-9)
        drop = int(((ref[..., 3] > 0.05) & (ims[..., 3] <= 0.0)).sum())
        rows[name] = {"curve": dev.tolist(), "alpha_deviation_max": float(dev.max()),
                      "dropouts": drop}
    return {"angles": angles.tolist(), "rows": rows}


def s8(args):
    meta = json.loads((DATA / "ct_head_invesalius.json").read_text())
    array = np.load(DATA / "ct_head_invesalius.npy")
    vevm = VolumeEVM.from_array(array, -300, spacing=tuple(meta["spacing_mm"]))
    tf = TransferFunction.preset("ct_bone")
    cam = orbit(vevm, (0.3, -1.0, 0.4), (0, 0, 1), args.size)
    thresholds = (0.9, 0.95, 0.99, 0.999, 1.0)
    rows = {}
    for method in ("shear_warp", "splat", "raycast"):
        images, times = [], []
        for t in thresholds:
            render(vevm, cam, tf, method=method, termination=t)  # warm-up
            t0 = time.perf_counter()
            images.append(render(vevm, cam, tf, method=method, termination=t)[0])
            times.append(time.perf_counter() - t0)
        full = images[-1].astype(np.float64)
        dev = [float(np.abs(im - full).max()) for im in images[:-1]]
        rows[method] = {"frame_s": times, "max_abs_vs_no_termination": dev,
                        "bound_held": all(d <= 1 - t + 1e-6 for d, t in zip(dev, thresholds))}
    return {"thresholds": list(thresholds), "rows": rows}


TESTS = {"s1": s1, "s2": s2, "s3": s3, "s4": s4, "s5": s5, "s6": s6, "s8": s8}
X_AXES = {"s1": ("angles", "angle about x (°)"), "s2": ("angles", "angle about (1,1,1) (°)"),
          "s3": ("zooms", "pixels per voxel"), "s4": ("steps_voxels", "ray step (voxels)"),
          "s5": ("widths", "pulse width (fraction of range)"),
          "s6": ("angles", "plate angle (°)"), "s8": ("thresholds", "termination threshold")}


# ----------------------------------------------------------------------------- outputs
def chart(path, name, result):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    key, xlabel = X_AXES[name]
    x = result[key]
    fig, ax = plt.subplots(figsize=(7, 4))
    for variant, row in result["rows"].items():
        y = row.get("curve", row.get("max_abs_vs_no_termination"))
        ax.plot(x[:len(y)], y, marker=".", lw=1, label=variant)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("relative alpha deviation" if name == "s6" else
                  "max |image - no termination|" if name == "s8" else "RMSE vs reference")
    if name in ("s3", "s4", "s5"):
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"{name.upper()}", fontsize=9)
    fig.tight_layout()
    write_atomically(path, lambda temporary: fig.savefig(temporary, dpi=80, format="png"),
                     overwrite=True)
    plt.close(fig)


def markdown(results, facts, size):
    """One table per test: a column per swept value when the sweep is short (S3, S4, S5, S8),
    else the summary measures of the sweep."""
    lines = [f"# Stability suite at {size}² (commit {facts['commit'][:10]}, "
             f"{facts['date_utc']})", ""]
    for name, r in results.items():
        key, xlabel = X_AXES[name]
        x = r[key]
        first = next(iter(r["rows"].values()))
        measures = [k for k, v in first.items() if not isinstance(v, list)]
        series = [k for k, v in first.items() if isinstance(v, list)] if len(x) <= 8 else []
        lines += [f"## {name.upper()}" + (f" (columns @: {xlabel})" if series else ""), ""]
        head = measures + [f"{'RMSE' if k == 'curve' else k} @ {v:g}" for k in series for v in x]
        lines += ["| variant | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
        for variant, row in r["rows"].items():
            cells = [f"{row[k]:.4g}" if isinstance(row[k], float) else str(row[k])
                     for k in measures]
            cells += [f"{v:.4g}" for k in series for v in row[k]]
            cells += [""] * (len(head) - len(cells))
            lines.append(f"| {variant} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--size", type=int, default=128, help="image side (pixels)")
    parser.add_argument("--tests", default=",".join(TESTS))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    facts = run_facts()
    results = {}
    for name in [t for t in args.tests.split(",") if t]:
        t0 = time.perf_counter()
        print(f"[bench_stability] {name} ...", flush=True)
        results[name] = TESTS[name](args)
        print(f"[bench_stability] {name} done in {time.perf_counter() - t0:.0f} s", flush=True)
        chart(args.out / f"stability_{name}.png", name, results[name])
    text = markdown(results, facts, args.size)
    print(text)
    write_atomically(args.out / "stability.md", lambda t: t.write_text(text), overwrite=True)
    write_json(args.out / "stability.json", {"benchmark": "stability", **facts,
                                             "size": args.size, "results": results})


if __name__ == "__main__":
    main()
