"""The demo (``make demo``, ``sample_blends/make_demo.py``) on the real CT head, small: it runs
to the end and writes the still, the turntable frames and an MP4 Blender reads back."""

import subprocess
import sys

import numpy as np
import pytest

from blender_helpers import REPO

FRAMES = 24


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory, data_dir):
    out = tmp_path_factory.mktemp("demo")
    run = subprocess.run([sys.executable, str(REPO / "sample_blends" / "make_demo.py"),
                          "--out", str(out), "--scan", str(data_dir / "ct_head_invesalius.npy"),
                          "--size", "96", "--turntable-size", "64", "--frames", str(FRAMES)],
                         capture_output=True, text=True, timeout=600, cwd=out)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "[demo] done" in run.stdout
    return out


def test_the_demo_writes_a_turntable_movie_of_all_its_frames(demo_out):
    import bpy

    frames = sorted((demo_out / "turntable").glob("frame_*.png"))
    assert [p.name for p in frames] == [f"frame_{n:04d}.png" for n in range(1, FRAMES + 1)]
    clip = bpy.data.movieclips.load(str(demo_out / "turntable.mp4"))
    try:
        assert clip.frame_duration >= FRAMES
    finally:
        bpy.data.movieclips.remove(clip)


def rgb_of(path):
    """An image file's pixels, (height, width, 3) float32, bottom row first."""
    import bpy

    image = bpy.data.images.load(str(path))
    try:
        width, height = image.size
        rgba = np.empty(width * height * 4, np.float32)
        image.pixels.foreach_get(rgba)
    finally:
        bpy.data.images.remove(image)
    return rgba.reshape(height, width, 4)[..., :3]


def not_world(rgb):
    """Where an image shows something other than the world colour (its corner pixel)."""
    return np.abs(rgb - rgb[0, 0]).max(axis=-1) > 0.2


def test_the_demo_still_shows_the_volume_over_the_scene(demo_out):
    rgb = rgb_of(demo_out / "demo.png")
    height, width = rgb.shape[:2]
    background = rgb[0, 0]  # a corner: the world colour (the head is framed in the middle)
    bone = not_world(rgb)
    # The bone's DVR fills a good part of the middle and is brighter than the world.
    middle = bone[height // 4: 3 * height // 4, width // 4: 3 * width // 4]
    assert middle.mean() > 0.3
    assert rgb[bone].mean() > background.mean() + 0.2
    assert not bone[:, :2].any() and not bone[:2, :].any()  # framed: the edges are world


def test_cycles_renders_the_native_volume_where_the_dvr_shows_the_bone(demo_out):
    """demo_cycles.png (Cycles alone, the region as a native Volume, half the size) covers the
    same pixels as our DVR's composite: the two renderers place the volume alike."""
    dvr = not_world(rgb_of(demo_out / "demo.png"))[::2, ::2]
    cycles = not_world(rgb_of(demo_out / "demo_cycles.png"))
    assert cycles.shape == dvr.shape
    assert (dvr & cycles).sum() / (dvr | cycles).sum() > 0.7
