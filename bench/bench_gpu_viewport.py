"""Frame time of the Viewport DVR's drawing: the CT head at 256², 512² and 1280×720, resting and
moving quality.

Each frame is what the viewport's draw handler does for one volume (``gpu_viewport.draw_volume``
with the options ``gpu_viewport.draw_options`` gives at rest and while the view moves): read the
depth buffer back and convert it, compute the frame's uniforms (level Auto, the Render settings'
default quality and termination), draw, over an offscreen of the image's size cleared to the
background; one pixel read back afterwards waits for the GPU to finish. The first frame of each
size (textures, shader) is not timed. Run it with a Python that has the ``bpy`` module (it makes
a GPU context in background mode; here Mesa llvmpipe, software OpenGL):

    python bench/bench_gpu_viewport.py [--out bench/results] [--repeat 5]

Prints a Markdown table and writes ``bench_gpu_viewport.json`` in ``--out``.
"""

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._common import REPO, run_facts, write_json  # noqa: E402
from bench.bench_dvr import scene  # noqa: E402
from volumeevm_addon.rendering import method_options

SIZES = ((256, 256), (512, 512), (1280, 720))
"""Image sizes (width, height)."""


def frame_times(vevm, cam, tf, size, repeat):
    """Seconds per frame at rest and moving (each a list of ``repeat``), and the level each
    drew."""
    import gpu
    from volumeevm.blender import gpu_draw, gpu_textures, gpu_viewport

    w, h = size
    cam = dataclasses.replace(cam, resolution_x=w, resolution_y=h, resolution_percentage=100)
    projection, view = cam.matrix_projection(), np.linalg.inv(cam.matrix_world)
    options = method_options(gpu_draw.METHOD, 1.0, tuple(vevm.spacing), termination=0.99,
                             level="auto")
    offscreen = gpu.types.GPUOffScreen(w, h)
    pixel = gpu_textures.float_buffer(np.zeros(4, np.float32))
    times, levels = {}, {}
    try:
        with offscreen.bind():
            framebuffer = gpu.state.active_framebuffer_get()
            for quality, moving in (("resting", False), ("moving", True)):
                drawn = gpu_viewport.draw_options(options, moving)
                times[quality] = []
                for i in range(repeat + 1):
                    framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
                    start = time.perf_counter()
                    levels[quality] = gpu_viewport.draw_volume(vevm, tf, projection, view, size,
                                                               **drawn)
                    framebuffer.read_color(w // 2, h // 2, 1, 1, 4, 0, "FLOAT", data=pixel)
                    if i:  # the first: textures and shader made
                        times[quality].append(time.perf_counter() - start)
    finally:
        offscreen.free()
    return times, levels


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    import bpy  # noqa: F401  (it makes the gpu module importable)
    import gpu

    from sample_blends.make_demo import load_extension

    load_extension()
    from volumeevm.blender import gpu_context

    gpu_context.ensure_context()
    vevm, cam, tf = scene("ct_head", "persp")
    renderer = gpu.platform.renderer_get()
    rows = []
    print(f"CT head {vevm.shape[0]}x{vevm.shape[1]}x{vevm.shape[2]}, perspective, on {renderer}"
          f" (median of {args.repeat} frames, seconds)\n")
    print("| image | resting | moving | speed-up | levels (resting, moving) |")
    print("|---|---|---|---|---|")
    for size in SIZES:
        times, levels = frame_times(vevm, cam, tf, size, args.repeat)
        rest, move = statistics.median(times["resting"]), statistics.median(times["moving"])
        rows.append({"width": size[0], "height": size[1], "levels": levels,
                     "resting_s": times["resting"], "moving_s": times["moving"]})
        print(f"| {size[0]}×{size[1]} | {rest:.3f} | {move:.3f} | {rest / move:.1f}× "
              f"| {levels['resting']}, {levels['moving']} |", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "bench_gpu_viewport.json",
               {"facts": {**run_facts(), "renderer": renderer, "repeat": args.repeat},
                "dataset": "ct_head", "view": "persp", "rows": rows})


if __name__ == "__main__":
    main()
