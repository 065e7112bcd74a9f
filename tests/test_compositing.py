"""Laying a volume render over a scene render: premultiplied alpha over, and the output depth
(the volume's where it is seen, else the scene's)."""

import numpy as np
import pytest

from volumeevm_addon import VolumeEVMError
from volumeevm_addon.rendering import BACKGROUND_DEPTH, composite_over, output_depth


def test_over_is_dvr_plus_the_scene_through_what_the_dvr_lets_pass():
    rng = np.random.default_rng(5)
    alpha = rng.random((6, 7, 1))
    dvr = np.concatenate([rng.random((6, 7, 3)) * alpha, alpha], axis=-1)  # premultiplied
    scene = np.concatenate([rng.random((6, 7, 3)), np.ones((6, 7, 1))], axis=-1)
    out = composite_over(dvr, scene)
    assert out.dtype == np.float32 and out.shape == (6, 7, 4)
    dvr32, scene32 = dvr.astype(np.float32), scene.astype(np.float32)
    np.testing.assert_array_equal(out, dvr32 + (1 - dvr32[..., 3:4]) * scene32)
    np.testing.assert_allclose(out[..., 3], 1.0, rtol=1e-6)  # over an opaque scene: opaque


def test_over_known_answers():
    scene = np.array([[[0.0, 0.0, 1.0, 1.0], [0.2, 0.4, 0.6, 1.0], [0.3, 0.3, 0.3, 0.5]]])
    dvr = np.array([[[1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], [0.25, 0.0, 0.0, 0.5]]])
    expected = np.array([[[1.0, 0.0, 0.0, 1.0],  # opaque volume: only the volume
                          [0.2, 0.4, 0.6, 1.0],  # no volume: only the scene
                          [0.4, 0.15, 0.15, 0.75]]], np.float32)  # half and half
    np.testing.assert_allclose(composite_over(dvr, scene), expected, rtol=1e-7)


@pytest.mark.parametrize("dvr_shape, scene_shape", [
    ((4, 5, 4), (4, 6, 4)), ((4, 5, 3), (4, 5, 3)), ((4, 5), (4, 5)), ((2, 4, 5, 4), (2, 4, 5, 4)),
])
def test_over_refuses_images_that_do_not_match(dvr_shape, scene_shape):
    with pytest.raises(VolumeEVMError, match=r"dvr_rgba .* and scene_rgba .*: expected the same "
                                             r"\(H, W, 4\) shape"):
        composite_over(np.zeros(dvr_shape), np.zeros(scene_shape))


def test_output_depth_is_the_volumes_where_seen_else_the_scenes():
    dvr_depth = np.array([[0.5, BACKGROUND_DEPTH, 3.0], [BACKGROUND_DEPTH, 2.0, 1e9]])
    scene_depth = np.array([[1.0, 4.0, 2.0], [BACKGROUND_DEPTH, 1.5, BACKGROUND_DEPTH]])
    out = output_depth(dvr_depth, scene_depth)
    assert out.dtype == np.float32
    # The volume's depth wherever it saw something, even behind the scene's (its rays stopped
    # there, so a depth beyond the scene's cannot come from a real render).
    np.testing.assert_array_equal(out, np.array([[0.5, 4.0, 3.0], [BACKGROUND_DEPTH, 2.0, 1e9]],
                                                np.float32))


def test_output_depth_refuses_images_that_do_not_match():
    with pytest.raises(VolumeEVMError, match=r"dvr_depth \(2, 3\) and scene_depth \(3, 2\)"):
        output_depth(np.zeros((2, 3)), np.zeros((3, 2)))
    with pytest.raises(VolumeEVMError, match="expected the same"):
        output_depth(np.zeros(3), np.zeros(3))
