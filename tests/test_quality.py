"""One quality setting for every method: the render options it means, each given only to the
method that takes it."""

import numpy as np
import pytest

from volumeevm_addon import LEVELS, METHODS, VolumeEVMError
from volumeevm_addon.rendering import method_options, render_options

SPACING = (0.8, 0.5, 1.25)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("level", LEVELS)
def test_every_option_is_one_the_method_takes(method, level):
    options = method_options(method, 1.5, SPACING, shading=True, level=level,
                             slices_per_voxel=2, classification="post", jitter=True,
                             preintegrate=True)
    assert options["level"] == level and options["shading"] is True
    assert set(options) - {"level"} <= set(render_options(method)), method


def test_quality_scales_each_methods_sampling():
    assert method_options("shear_warp", 2.0, SPACING) == {
        "termination": 0.99, "level": "auto", "intermediate_scale": 2.0,
        "slices_per_voxel": 1, "classification": "pre"}
    for method in ("raycast", "raycast_navigate"):
        assert method_options(method, 2.0, SPACING, termination=0.9, jitter=True) == {
            "termination": 0.9, "level": "auto", "step_mm": 0.125, "jitter": True,
            "preintegrate": False}
    reference = method_options("reference", 2.0, SPACING, level="full")
    assert reference == {"level": "full", "step_mm": 0.5 / 16 / 2}  # no early termination
    assert "shading" not in reference  # passed only when on


@pytest.mark.parametrize("quality, substeps", [(0.05, 1), (0.5, 1), (1.0, 1), (1.6, 2), (3.0, 3)])
def test_splatting_quality_is_its_sub_slabs_per_sheet(quality, substeps):
    assert method_options("splat", quality, SPACING)["substeps"] == substeps


@pytest.mark.parametrize("kwargs, match", [
    (dict(method="phong"), "method: one of"),
    (dict(quality=0.0), "quality: must be > 0, got 0.0"),
    (dict(quality=-1.0), "quality: must be > 0"),
    (dict(quality=np.nan), "quality: must be > 0, got nan"),
    (dict(level="half"), "level: one of"),
    (dict(spacing=(1.0, 1.0)), "spacing: three positive voxel sizes"),
    (dict(spacing=(1.0, 0.0, 1.0)), "spacing: three positive voxel sizes"),
    (dict(spacing=(1.0, np.inf, 1.0)), "spacing: three positive voxel sizes"),
])
def test_bad_settings_raise_naming_the_parameter(kwargs, match):
    arguments = dict(method="raycast", quality=1.0, spacing=SPACING) | kwargs
    with pytest.raises(VolumeEVMError, match=match):
        method_options(arguments.pop("method"), arguments.pop("quality"),
                       arguments.pop("spacing"), **arguments)
