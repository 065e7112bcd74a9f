"""DVR benchmark: our methods and the peers side by side in one run (issue 4).

Cases (real volumes from ../shared/data):

- ``brainsmall``: VolPack's own example volume (MRI, 128x128x84 uint8, spacing unknown, taken as
  1 mm isotropic), preset ``mri`` over 0..202, region of interest ``density >= 20`` (the transfer
  function is transparent below 30), 256x256 image;
- ``ct_head``: InVesalius CT head (256x256x108 int16 HU, 0.957x0.957x1.5 mm), preset ``ct_bone``
  (transparent below 150 HU), region ``HU >= -300``, 512x512 image.

Views: one oblique orthographic camera per case (every method and both peers) and one perspective
camera at the same direction (ours and VTK; VolPack has no perspective projection). The cameras
frame the volume's box.

Methods: every method of :data:`volumeevm_addon._render.METHODS` that exists when the bench runs
(the others are listed as missing, never timed), at default quality, mode "over". Peers:

- VolPack (``bench/peers/volpack_driver.c`` linked with Debian's ``libvolpack.a``), run twice:
  ``volpack`` with its defaults (no voxel skipping, no early ray termination: ``VP_MIN_VOXEL_
  OPACITY`` 0, ``VP_MAX_RAY_OPACITY`` 1) and ``volpack_fast`` with the values its manual suggests
  (0.05, 0.95). Frame time = ``vpRenderClassifiedVolume``; classification timed apart.
- VTK ``vtkFixedPointVolumeRayCastMapper`` offscreen (EGL), ``vtk`` at its default sample distance
  (1 mm) and ``vtk_fine`` at 0.25 mm. Frame time = ``vtkRenderWindow.Render()``.

How the peers are matched (view, transfer function, voxel-centre shift, image conversion) is
written in ``bench/peers/volpack_peer.py`` and ``bench/peers/vtk_peer.py``.

Error: mean absolute error (MAE) and RMSE over all pixels and the four channels of premultiplied
RGBA against the dense float64 reference renderer (``method="reference"``, step voxel/16, no
early termination) **of the scene the method was given**: our methods render the VolumeEVM
(region of interest, boundary policy "clamp"), so they are compared with the reference of that
VolumeEVM; the peers render the whole dense volume, so they are compared with the reference of
the whole volume (a VolumeEVM of every voxel). The difference between the two references is
printed too (the region's own effect, not an error of any method). Peers' images are 8-bit.

Timing: best of ``--repeat`` warm runs (after one untimed warm-up that is also reported as the
first-call time); the machine has 2 cores shared with other work, so timings are noisy: compare
ratios, not absolute numbers. A method whose warm-up takes longer than ``--budget`` seconds is
timed by that single run. Memory: peak of Python/NumPy allocations during one render
(``tracemalloc``) for ours; the peers' own process peak RSS (``getrusage``).

References are slow (seconds to minutes): they are cached in ``bench/results/cache/`` keyed by a
hash of the scene and of ``_reference.py``.

Usage: ``python bench/bench_dvr.py [--out bench/results] [--repeat 5] [--cases brainsmall,ct_head]``
"""

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench" / "peers"))

from bench._common import run_facts, write_json  # noqa: E402
from volumeevm_addon._files import write_atomically  # noqa: E402
from volumeevm_addon import VolumeEVM  # noqa: E402
from volumeevm_addon._camera import Camera  # noqa: E402
from volumeevm_addon._render import METHODS, render  # noqa: E402
from volumeevm_addon._transfer import TransferFunction  # noqa: E402
from volumeevm_addon._volume import BLENDER_UNITS_PER_MM, grid_to_world  # noqa: E402

DATA = REPO.parent / "shared" / "data"
OURS = tuple(m for m in METHODS if m != "reference")
CASES = {
    "brainsmall": {"file": "mr_brainsmall_volpack", "preset": "mri", "data_range": (0, 202),
                   "threshold": 20, "size": 256, "azimuth": 30.0, "elevation": 20.0},
    "ct_head": {"file": "ct_head_invesalius", "preset": "ct_bone", "data_range": None,
                "threshold": -300, "size": 512, "azimuth": 215.0, "elevation": 20.0},
}
PEERS_ORTHO = (("volpack", {"min_voxel_opacity": 0.0, "max_ray_opacity": 1.0}),
               ("volpack_fast", {"min_voxel_opacity": 0.05, "max_ray_opacity": 0.95}))
PEERS_VTK = (("vtk", {"sample_distance": 1.0}), ("vtk_fine", {"sample_distance": 0.25}))
TARGETS = {"shear_warp_time_vs_volpack_max": 3.0, "best_speedup_vs_vtk_at_vtk_error_min": 2.0}


# ----------------------------------------------------------------------------- scene
def load_case(name):
    spec = CASES[name]
    meta = json.loads((DATA / f"{spec['file']}.json").read_text())
    array = np.load(DATA / f"{spec['file']}.npy")
    spacing = tuple(float(s) for s in meta["spacing_mm"])
    if spec["preset"] in ("mri", "microscopy"):
        tf = TransferFunction.preset(spec["preset"], data_range=spec["data_range"])
    else:
        tf = TransferFunction.preset(spec["preset"])
    return spec, meta, array, spacing, tf


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


def cameras(spec, shape, g):
    """The oblique orthographic and perspective cameras of a case, framing the volume's box."""
    corners = box_corners(shape, g)
    center = corners.mean(axis=0)
    radius = float(np.linalg.norm(corners - center, axis=1).max())
    size = spec["size"]
    up, front = spec.get("up", (0.0, 0.0, 1.0)), spec.get("front", (0.0, -1.0, 0.0))
    m = look_from(center, spec["azimuth"], spec["elevation"], 2.0 * radius, up, front)
    rinv = np.linalg.inv(m[:3, :3])
    local = (corners - m[:3, 3]) @ rinv.T
    ortho_scale = 1.02 * 2.0 * float(np.abs(local[:, :2]).max())
    ortho = Camera.orthographic(m, ortho_scale, resolution_x=size, resolution_y=size,
                                clip_start=0.001, clip_end=10.0 * radius)
    mp = look_from(center, spec["azimuth"], spec["elevation"], 2.5 * radius, up, front)
    local = (corners - mp[:3, 3]) @ np.linalg.inv(mp[:3, :3]).T
    tan_half = 1.02 * float(np.max(np.abs(local[:, :2]) / -local[:, 2:3]))
    lens = 18.0 / tan_half  # sensor 36 mm, horizontal fit (square image)
    persp = Camera.perspective(mp, lens, sensor_width=36.0, resolution_x=size,
                               resolution_y=size, clip_start=0.001, clip_end=10.0 * radius)
    return {"ortho": ortho, "persp": persp}


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


def reference(vevm, cam, tf, cache_dir, label, extra):
    """The reference image of this VolumeEVM and view, from the cache or rendered and cached."""
    oracle = _sha((REPO / "volumeevm_addon" / "_reference.py").read_bytes())
    key_src = json.dumps({"camera": camera_record(cam), "tf": np.asarray(tf.points).tolist(),
                          "unit": tf.unit_length_mm, "shape": vevm.shape,
                          "spacing": vevm.spacing, "voxels": vevm.voxel_count,
                          "table": _sha(np.ascontiguousarray(vevm.table(0)).tobytes()),
                          "oracle": oracle, **extra}, sort_keys=True)
    key = _sha(key_src.encode())[:20]
    path = cache_dir / f"ref_{label}_{key}.npz"
    if path.exists():
        with np.load(path) as cached:
            return cached["rgba"], float(cached["seconds"]), True
    print(f"[bench_dvr]   rendering reference {label} (cached afterwards) ...", flush=True)
    t0 = time.perf_counter()
    rgba, _ = render(vevm, cam, tf, method="reference")
    seconds = time.perf_counter() - t0
    cache_dir.mkdir(parents=True, exist_ok=True)
    ignore = cache_dir / ".gitignore"
    if not ignore.exists():  # the cache never goes into git
        ignore.write_text("*\n")
    write_atomically(path, lambda temporary: np.savez(temporary, rgba=rgba, seconds=seconds,
                                                      key=key_src), overwrite=True)
    return rgba, seconds, False


# ----------------------------------------------------------------------------- measuring
def errors(img, ref):
    d = img.astype(np.float64) - ref.astype(np.float64)
    return {"mae": float(np.abs(d).mean()), "rmse": float(np.sqrt((d * d).mean())),
            "mae_alpha": float(np.abs(d[..., 3]).mean()), "max_abs": float(np.abs(d).max())}


MODULES = {"shear_warp": ("_shear_warp", "render_shear_warp"), "splat": ("_splat", "render_splat"),
           "raycast": ("_raycast", "render_raycast"),
           "raycast_navigate": ("_raycast", "render_raycast_navigate")}


def method_call(method):
    """A function ``f(vevm, cam, tf) -> rgba`` for ``method``, and a note, or ``(None, reason)``
    when the method does not exist yet.

    Normally this is :func:`render`. ``render`` imports every method's module at once, so while
    one of them is still missing it raises ImportError for all; the methods that do exist are
    then called the way ``render`` calls them (same grid-to-world matrix, same arguments).
    """
    import importlib

    try:
        from volumeevm_addon._render import _renderers

        _renderers()
        return (lambda vevm, cam, tf: render(vevm, cam, tf, method=method)[0]), None
    except ImportError as exc:
        why = str(exc)
    module, func = MODULES[method]
    try:
        fn = getattr(importlib.import_module(f"volumeevm_addon.{module}"), func)
    except (ImportError, AttributeError) as exc:
        return None, f"not available: {exc}"

    def call(vevm, cam, tf):
        to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, None)
        return fn(vevm, cam, tf, to_world, mode="over", depth_in=None)[0]

    return call, f"called directly: render() cannot import every method yet ({why})"


def time_ours(call, vevm, cam, tf, repeat, budget):
    """Warm-up under tracemalloc (first-call time and peak allocations), then best of
    ``repeat`` warm runs within ``budget`` seconds."""
    tracemalloc.start()
    t0 = time.perf_counter()
    rgba = call(vevm, cam, tf)
    first = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    times = []
    if first <= budget:
        spent = 0.0
        for _ in range(repeat):
            t0 = time.perf_counter()
            rgba = call(vevm, cam, tf)
            dt = time.perf_counter() - t0
            times.append(dt)
            spent += dt
            if spent > budget:
                break
    best = min(times) if times else first
    return rgba, {"first_s": first, "best_s": best, "runs": len(times) or 1,
                  "peak_alloc_mb": peak / 2 ** 20}


# ----------------------------------------------------------------------------- run
def run_case(name, args, rows, notes):
    spec, meta, array, spacing, tf = load_case(name)
    print(f"[bench_dvr] {name}: {array.shape} {array.dtype}, spacing {spacing} mm, "
          f"TF {tf.name}, region >= {spec['threshold']}, {spec['size']}^2", flush=True)
    t0 = time.perf_counter()
    vevm = VolumeEVM.from_array(array, spec["threshold"], spacing=spacing)
    build_s = time.perf_counter() - t0
    full = VolumeEVM.from_array(array, float(array.min()), spacing=spacing)
    g = grid_to_world(spacing, (0.0, 0.0, 0.0))
    size = vevm.size_report()
    case_info = {"case": name, "shape": list(array.shape), "dtype": str(array.dtype),
                 "spacing_mm": list(spacing), "tf": tf.name, "tf_points": np.asarray(
                     tf.points).tolist(), "unit_length_mm": tf.unit_length_mm,
                 "region_threshold": spec["threshold"], "region_voxels": vevm.voxel_count,
                 "voxels": int(array.size), "evm_vertices": len(vevm.evm),
                 "vevm_build_s": build_s, "vevm_bytes": size["total_bytes"],
                 "dense_bytes": size["dense_bytes"], "views": {}}
    den = Path("/usr/share/doc/libvolpack1-dev/examples/brainsmall.den")
    if name == "brainsmall" and den.exists():  # the .npy is VolPack's own example volume
        raw = den.read_bytes()
        case_info["same_bytes_as_volpack_den"] = (
            np.ascontiguousarray(array.T).tobytes() == raw[len(raw) - array.size:])
    cams = cameras(spec, array.shape, g)
    cache_dir = args.out / "cache"
    for view, cam in cams.items():
        case_info["views"][view] = camera_record(cam)
        print(f"[bench_dvr]  view {view} ({cam.width}x{cam.height})", flush=True)
        ref_voi, ref_voi_s, hit1 = reference(vevm, cam, tf, cache_dir, f"{name}_{view}_voi",
                                             {"threshold": spec["threshold"]})
        ref_full, ref_full_s, hit2 = reference(full, cam, tf, cache_dir, f"{name}_{view}_full",
                                               {"threshold": "all"})
        base = {"case": name, "view": view, "size": f"{cam.width}x{cam.height}"}
        rows.append({**base, "method": "reference", "kind": "oracle", "best_s": ref_voi_s,
                     "first_s": ref_voi_s, "runs": 1, "cached": hit1,
                     "ref_full_s": ref_full_s,
                     "region_vs_full": errors(ref_voi, ref_full),
                     "note": "dense float64 ray caster, step voxel/16; the region's reference "
                             "(error columns: region reference vs whole-volume reference)"})
        images = {"reference": ref_voi}
        for method in args.methods:
            call, reason = method_call(method)
            how = None
            if call is not None:
                how, reason = reason, None
                try:
                    rgba, timing = time_ours(call, vevm, cam, tf, args.repeat, args.budget)
                except (NotImplementedError, ImportError) as exc:
                    reason = f"{type(exc).__name__}: {exc}"
                except Exception as exc:  # a method that fails here is reported, not hidden
                    reason = f"failed: {type(exc).__name__}: {exc}"
            if reason is not None:
                rows.append({**base, "method": method, "kind": "ours", "missing": reason})
                print(f"[bench_dvr]   {method:18s} missing ({reason})", flush=True)
                continue
            images[method] = rgba
            row = {**base, "method": method, "kind": "ours", **timing,
                   "error": errors(rgba, ref_voi), "error_vs_full_ref": errors(rgba, ref_full)}
            if how:
                row["note"] = how
            rows.append(row)
            print(f"[bench_dvr]   {method:18s} {timing['best_s']:9.4f} s  "
                  f"MAE {row['error']['mae']:.5f}", flush=True)
        # peers
        peer_runs = []
        if "volpack" in args.peers and cam.is_ortho:
            peer_runs += [(n, "volpack", o) for n, o in PEERS_ORTHO]
        elif "volpack" in args.peers:
            rows.append({**base, "method": "volpack", "kind": "peer",
                         "missing": "VolPack has no perspective projection"})
        if "vtk" in args.peers:
            peer_runs += [(n, "vtk", o) for n, o in PEERS_VTK]
        for label, peer, opts in peer_runs:
            try:
                info = run_peer(peer, array, g, spacing, cam, tf, opts, args)
            except Exception as exc:
                reason = f"{type(exc).__name__}: {exc}"
                rows.append({**base, "method": label, "kind": "peer", "missing": reason})
                notes.append(f"{name}/{view}/{label}: {reason}")
                print(f"[bench_dvr]   {label:18s} failed ({reason})", flush=True)
                continue
            rgba = info.pop("rgba")
            images[label] = rgba
            row = {**base, "method": label, "kind": "peer", "best_s": info.pop("best_s"),
                   "first_s": None, "runs": len(info.get("frames_s", [])),
                   "max_rss_mb": info.get("max_rss_kb", 0) / 1024.0,
                   "error": errors(rgba, ref_full), "error_vs_region_ref": errors(rgba, ref_voi),
                   "settings": opts, "details": info}
            if peer == "volpack":
                row["preprocess_s"] = info.get("classify_s")
            rows.append(row)
            print(f"[bench_dvr]   {label:18s} {row['best_s']:9.4f} s  "
                  f"MAE {row['error']['mae']:.5f}", flush=True)
        if args.images:
            save_panel(args.out / f"dvr_{name}_{view}.png", images)
    return case_info


def run_peer(peer, array, g, spacing, cam, tf, opts, args):
    if peer == "volpack":
        import volpack_peer

        reason = volpack_peer.available()
        if reason:
            raise RuntimeError(reason)
        return volpack_peer.render(array, g, spacing, cam, tf, frames=args.repeat, **opts)
    import vtk_peer

    return vtk_peer.render(array, g, cam, tf, mm_per_unit=1.0 / BLENDER_UNITS_PER_MM,
                           frames=args.repeat, **opts)


def save_panel(path, images, columns=4):
    """Images in a grid over black (premultiplied RGB is the composite over black), labelled."""
    try:
        from PIL import Image, ImageDraw
    except ImportError:
        return
    tiles = []
    for label, rgba in images.items():
        rgb = (np.clip(rgba[..., :3], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        tile = Image.fromarray(rgb)
        ImageDraw.Draw(tile).text((4, 4), label, fill=(255, 255, 0))
        tiles.append(tile)
    w, h = tiles[0].size
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    panel = Image.new("RGB", (w * cols, h * rows))
    for i, tile in enumerate(tiles):
        panel.paste(tile, ((i % cols) * w, (i // cols) * h))
    if panel.width > 1024:
        f = 1024 / panel.width
        panel = panel.resize((1024, max(1, int(panel.height * f))))
    write_atomically(path, lambda temporary: panel.save(temporary, format="PNG"), overwrite=True)


def save_chart(path, rows):
    """Frame time against MAE (log-log), one panel per case and view; needs matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    panels = sorted({(r["case"], r["view"]) for r in rows})
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 4.2), squeeze=False)
    for ax, (case, view) in zip(axes[0], panels):
        for r in rows:
            if (r["case"], r["view"]) != (case, view) or "error" not in r:
                continue
            colour = "tab:blue" if r["kind"] == "ours" else "tab:red"
            mae = max(r["error"]["mae"], 1e-6)
            ax.scatter(r["best_s"], mae, color=colour, marker="o" if r["kind"] == "ours" else "s")
            ax.annotate(r["method"], (r["best_s"], mae), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("frame time (s, best of N)")
        ax.set_ylabel("MAE of premultiplied RGBA vs reference")
        ax.set_title(f"{case} {view}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("VolumeEVM DVR: ours (blue) and peers (red)", fontsize=10)
    fig.tight_layout()
    write_atomically(path, lambda temporary: fig.savefig(temporary, dpi=90, format="png"),
                     overwrite=True)
    plt.close(fig)
    return True


# ----------------------------------------------------------------------------- report
def targets(rows):
    """The issue's two targets per case (orthographic view), stated plainly."""
    out = []
    for case in sorted({r["case"] for r in rows}):
        sel = {r["method"]: r for r in rows if r["case"] == case and r["view"] == "ortho"}
        sw, vp, vt = sel.get("shear_warp"), sel.get("volpack"), sel.get("vtk")
        entry = {"case": case}
        if sw and "best_s" in sw and vp and "best_s" in vp:
            ratio = sw["best_s"] / vp["best_s"]
            entry["shear_warp_time_over_volpack"] = ratio
            entry["shear_warp_mae"] = sw["error"]["mae"]
            entry["volpack_mae"] = vp["error"]["mae"]
            entry["shear_warp_target_met"] = bool(
                ratio <= TARGETS["shear_warp_time_vs_volpack_max"]
                and sw["error"]["mae"] <= vp["error"]["mae"])
        else:
            entry["shear_warp_target_met"] = None
            entry["shear_warp_note"] = "shear_warp or volpack missing"
        if vt and "best_s" in vt:
            ours = [r for m, r in sel.items() if r.get("kind") == "ours" and "best_s" in r
                    and r["error"]["mae"] <= vt["error"]["mae"]]
            entry["vtk_s"], entry["vtk_mae"] = vt["best_s"], vt["error"]["mae"]
            if ours:
                best = min(ours, key=lambda r: r["best_s"])
                entry["best_at_vtk_error"] = best["method"]
                entry["speedup_vs_vtk"] = vt["best_s"] / best["best_s"]
                entry["vtk_target_met"] = bool(
                    entry["speedup_vs_vtk"] >= TARGETS["best_speedup_vs_vtk_at_vtk_error_min"])
            else:
                entry["best_at_vtk_error"] = None
                entry["vtk_target_met"] = False
                entry["vtk_note"] = "no method of ours reaches VTK's error"
        out.append(entry)
    return out


def print_table(rows):
    head = (f"{'case':11s} {'view':6s} {'method':17s} {'frame s':>9s} {'first s':>9s} "
            f"{'MAE':>8s} {'RMSE':>8s} {'maxabs':>7s} {'mem MB':>8s}  note")
    print()
    print(head)
    print("-" * len(head))
    for r in rows:
        lead = f"{r['case']:11s} {r['view']:6s} {r['method']:17s}"
        if "missing" in r:
            print(f"{lead} {'-':>9s} {'-':>9s} {'-':>8s} {'-':>8s} {'-':>7s} {'-':>8s}  "
                  f"missing: {r['missing'][:70]}")
            continue
        if r["method"] == "reference":
            e = r["region_vs_full"]
            print(f"{lead} {r['best_s']:9.2f} {'':>9s} {e['mae']:8.5f} {e['rmse']:8.5f} "
                  f"{e['max_abs']:7.3f} {'':>8s}  region ref vs whole-volume ref"
                  f"{' (cached)' if r.get('cached') else ''}")
            continue
        e = r["error"]
        mem = r.get("peak_alloc_mb", r.get("max_rss_mb"))
        first = f"{r['first_s']:9.3f}" if r.get("first_s") is not None else f"{'':>9s}"
        note = ("tracemalloc peak" if r["kind"] == "ours" else
                f"peak RSS; vs whole-volume ref; best of {r['runs']}")
        if r.get("preprocess_s") is not None:
            note += f"; classify {r['preprocess_s']:.3f} s"
        if r.get("details", {}).get("rss_before_data_kb"):
            note += f"; {r['details']['rss_before_data_kb'] / 1024:.0f} MB before data"
        print(f"{lead} {r['best_s']:9.4f} {first} {e['mae']:8.5f} {e['rmse']:8.5f} "
              f"{e['max_abs']:7.3f} {mem:8.1f}  {note}")


def versions():
    out = {"python": platform.python_version(), "numpy": np.__version__}
    try:
        import scipy

        out["scipy"] = scipy.__version__
    except ImportError:
        pass
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
    parser.add_argument("--repeat", type=int, default=5, help="timed runs (best of)")
    parser.add_argument("--budget", type=float, default=60.0,
                        help="seconds of timed runs per method and view")
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--methods", default=",".join(OURS))
    parser.add_argument("--peers", default="volpack,vtk", help="'' for none")
    parser.add_argument("--no-images", dest="images", action="store_false")
    args = parser.parse_args()
    args.methods = [m for m in args.methods.split(",") if m]
    args.peers = [p for p in args.peers.split(",") if p]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, notes, cases = [], [], []
    load_start = os.getloadavg()
    facts = run_facts()  # the code measured is the code at the start
    for name in [c for c in args.cases.split(",") if c]:
        cases.append(run_case(name, args, rows, notes))
    print_table(rows)
    checks = targets(rows)
    missing = sorted({r["method"] for r in rows if "missing" in r and r["kind"] == "ours"})
    print()
    load = os.getloadavg()[0]
    print(f"Timing: best of {args.repeat} warm runs (after a warm-up) on {os.cpu_count()} cores "
          f"shared with other work (load average {load_start[0]:.1f} at start, {load:.1f} at end): "
          "noisy, compare ratios. Memory: ours = tracemalloc peak of one render; peers = "
          "process peak RSS (VmHWM).")
    if missing:
        print("Methods missing at run time: " + ", ".join(missing))
    for c in checks:
        print(f"targets {c['case']}: " + json.dumps({k: (round(v, 4) if isinstance(v, float)
                                                     else v) for k, v in c.items()
                                                    if k != "case"}))
    result = {
        "benchmark": "dvr",
        **facts,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {cpu_model()}",
        "threads_env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                                       "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")},
        "load_average_start_end": [round(load_start[0], 2), round(os.getloadavg()[0], 2)],
        "versions": versions(),
        "timing": f"best of {args.repeat} warm runs after one warm-up; budget {args.budget} s "
                  "per method and view; 2 cores shared with other work",
        "memory": "ours: tracemalloc peak during one render (Python/NumPy allocations); peers: "
                  "the peer process's peak RSS, VmHWM (VTK's includes the VTK libraries, see "
                  "details.rss_before_data_kb)",
        "error": "MAE/RMSE of premultiplied RGBA over all pixels and channels; ours vs the "
                 "reference of the region (VolumeEVM), peers vs the reference of the whole "
                 "volume; peers' 8-bit images /255",
        "targets": TARGETS,
        "target_results": checks,
        "missing_methods": missing,
        "notes": notes,
        "cases": cases,
        "rows": rows,
    }
    if args.images and save_chart(args.out / "dvr_speed_error.png", rows):
        print(f"wrote {args.out / 'dvr_speed_error.png'}")
    write_json(args.out / "bench_dvr.json", result)


if __name__ == "__main__":
    main()
