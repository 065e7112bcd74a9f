"""Our GPU method (``blender/gpu_draw.py``, Blender's ``gpu`` module) in the DVR benchmark.

It is ours, not a peer, but it runs like the peers: in a process of its own, here a Python with
the ``bpy`` module, which makes a GPU context in background mode (on this machine Mesa llvmpipe,
software OpenGL on the CPU cores; the chart names the renderer). :func:`render` runs this file
as a subprocess: the dataset and view go in by name (the process builds the same scene with
``bench_dvr.scene``), the settings as JSON; each setting is rendered once untimed, then
``frames`` times, and the images and times come back as an ``.npz``.
"""

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
TIMEOUT_S = 1800
"""Longest a dataset's GPU renders may take (all settings, on software OpenGL)."""


def render(dataset, view, settings, frames):
    """Render ``dataset``'s ``view`` with the GPU method once per option dict of ``settings``.

    Returns ``(renderer, results)``: the GPU's renderer string and, per setting, a dict with
    ``rgba`` (H, W, 4) premultiplied float32, row 0 at the top, and ``frames_s``. Raises
    RuntimeError when the process fails (no GPU context, no ``bpy``) or takes longer than
    :data:`TIMEOUT_S` (a Blender process that hangs must not hang the bench).
    """
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.npz"
        job = json.dumps({"dataset": dataset, "view": view, "settings": settings,
                          "frames": int(frames)})
        try:
            proc = subprocess.run([sys.executable, __file__, job, str(out)],
                                  capture_output=True, text=True, timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired as error:
            raise RuntimeError(f"GPU method: no answer in {TIMEOUT_S} s") from error
        if proc.returncode != 0 or not out.exists():
            raise RuntimeError(f"GPU method failed ({proc.returncode}): {proc.stderr[-2000:]}")
        with np.load(out) as data:
            meta = json.loads(str(data["meta"]))
            results = [{"rgba": data[f"rgba_{i}"], "frames_s": times}
                       for i, times in enumerate(meta["frames_s"])]
    return meta["renderer"], results


def _main(job, out):
    import bpy  # noqa: F401  (it makes the gpu module importable)
    import gpu

    sys.path[:0] = [str(REPO)]
    from bench.bench_dvr import scene
    from sample_blends.make_demo import load_extension

    load_extension()
    from volumeevm.blender import gpu_context, gpu_draw

    gpu_context.ensure_context()
    vevm, cam, tf = scene(job["dataset"], job["view"])
    arrays, times = {}, []
    for i, options in enumerate(job["settings"]):
        gpu_draw.render_gpu(vevm, cam, tf, **options)  # warm-up: textures and shader made
        frames = []
        for _ in range(job["frames"]):
            t0 = time.perf_counter()
            rgba, _, _ = gpu_draw.render_gpu(vevm, cam, tf, **options)
            frames.append(time.perf_counter() - t0)
        arrays[f"rgba_{i}"] = rgba
        times.append(frames)
    meta = {"renderer": gpu.platform.renderer_get(), "frames_s": times}
    np.savez(out, meta=json.dumps(meta), **arrays)


if __name__ == "__main__":
    _main(json.loads(sys.argv[1]), sys.argv[2])
