"""DVR image files: EXR (R, G, B, A, Z) round trip and PNG previews, atomic, never overwriting."""

import numpy as np
import pytest
from PIL import Image

from volumeevm_addon import VolumeEVMError, read_exr, write_exr, write_png


@pytest.fixture
def image():
    rng = np.random.default_rng(7)
    alpha = rng.random((5, 7, 1)).astype(np.float32)
    colour = rng.random((5, 7, 3)).astype(np.float32) * alpha  # premultiplied
    alpha[0, 0] = 0.0
    colour[0, 0] = 0.0
    depth = rng.random((5, 7)).astype(np.float32) * 3
    depth[0, 0] = 1e10
    return np.concatenate([colour, alpha], axis=2), depth


def test_exr_round_trip_keeps_every_channel_exactly(tmp_path, image):
    rgba, depth = image
    path = write_exr(tmp_path / "dvr.exr", rgba, depth)
    channels = read_exr(path)
    assert sorted(channels) == ["A", "B", "G", "R", "Z"]
    for i, name in enumerate("RGBA"):
        np.testing.assert_array_equal(channels[name], rgba[..., i])
    np.testing.assert_array_equal(channels["Z"], depth)
    assert [p.name for p in tmp_path.iterdir()] == ["dvr.exr"]


def test_png_preview_is_srgb_with_straight_alpha(tmp_path, image):
    rgba, _ = image
    path = write_png(tmp_path / "dvr.png", rgba)
    with Image.open(path) as png:
        assert png.mode == "RGBA" and png.size == (7, 5)
        pixels = np.asarray(png)
    alpha = rgba[..., 3:]
    straight = np.where(alpha > 0, rgba[..., :3] / np.where(alpha > 0, alpha, 1), 0)
    srgb = np.where(straight <= 0.0031308, 12.92 * straight, 1.055 * straight ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(pixels[..., :3] / 255, srgb, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(pixels[..., 3] / 255, alpha[..., 0], atol=0.5 / 255 + 1e-6)


def test_existing_files_are_kept_unless_overwrite(tmp_path, image):
    rgba, depth = image
    for name, write in (("user.exr", lambda p, **k: write_exr(p, rgba, depth, **k)),
                        ("user.png", lambda p, **k: write_png(p, rgba, **k))):
        path = tmp_path / name
        path.write_bytes(b"the user's file")
        with pytest.raises(VolumeEVMError, match=f"{name}: exists"):
            write(path)
        assert path.read_bytes() == b"the user's file"
        write(path, overwrite=True)
        assert path.read_bytes() != b"the user's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["user.exr", "user.png"]


def test_bad_images(tmp_path):
    with pytest.raises(VolumeEVMError, match=r"rgba: expected \(H, W, 4\)"):
        write_png(tmp_path / "x.png", np.zeros((4, 4, 3)))
    with pytest.raises(VolumeEVMError, match="depth: expected shape"):
        write_exr(tmp_path / "x.exr", np.zeros((4, 4, 4)), np.zeros((3, 3)))
    with pytest.raises(VolumeEVMError, match="is a folder"):
        write_png(tmp_path, np.zeros((4, 4, 4)))
