"""Every registered rendering method keeps its record's contract
(``volumeevm_addon.rendering.methods()``).

A method is one record (``Method``): what each field promises is checked here for every
record, so a new method is tested the day it is registered. The Blender side's half (the
sidebar's enum lists every record) is in ``test_blender_render.py``.
"""

import inspect

import numpy as np
import pytest

from volumeevm_addon import (
    METHODS,
    Camera,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    grid_to_world,
    phantoms,
    render,
)
from volumeevm_addon.rendering import Method, method_options, methods, render_options
from volumeevm_addon.rendering._render import _tables_to_build, render_memory

RECORDS = list(methods().values())
CPU = [record for record in RECORDS if record.render is not None]


def box_scene():
    """The 2x2x2 box of opacity 0.5 per mm in a 4³ grid of 0.5 mm voxels, seen along z by an
    orthographic 4x4 camera: alpha 1 - 0.5² = 0.75 over the four middle pixels, nothing
    elsewhere, depth at the box's top face (z = 2.5 mm = 0.0025 Blender units)."""
    vevm = VolumeEVM.from_volume(phantoms.box((4, 4, 4), lo=(1, 1, 1), hi=(3, 3, 3)), 0.5)
    camera = Camera.look_at((0.0015, 0.0015, 1.0), (0.0015, 0.0015, 0.0), (0.0, 1.0, 0.0),
                            ortho_scale=0.004, resolution_x=4, resolution_y=4)
    tf = TransferFunction([(0, 1, 1, 1, 0.5), (1, 1, 1, 1, 0.5)])
    return vevm, camera, tf


def test_the_registry_is_keyed_by_the_records_names_and_lists_every_cpu_method():
    assert [record.name for record in RECORDS] == list(methods())
    assert all(isinstance(record, Method) for record in RECORDS)
    assert tuple(record.name for record in CPU) == METHODS
    assert [record.name for record in RECORDS if record.gpu] == ["gpu"]


@pytest.mark.parametrize("record", RECORDS, ids=lambda r: r.name)
def test_record_fields(record):
    assert record.label.strip() and record.description.strip()
    assert render_options(record.name) == dict(record.options)
    assert all(isinstance(name, str) for name, _ in record.options)
    if record.render is None:  # drawn outside the core: a GPU method with a CPU fallback
        assert record.gpu and record.memory is None
        fallback = methods()[record.fallback]
        assert fallback.render is not None and not fallback.gpu
        assert fallback.categorical or not record.categorical
        with pytest.raises(VolumeEVMError, match=f"^method: '{record.name}' is drawn by "
                                                 f"Blender"):
            render(*box_scene(), method=record.name)
    else:
        assert record.fallback is None
        # One signature: (vevm, camera, tf, grid_to_world, *, mode, depth_in, **options).
        parameters = list(inspect.signature(record.render).parameters.values())
        assert [p.name for p in parameters[:4]] == ["vevm", "camera", "tf", "grid_to_world"]


@pytest.mark.parametrize("record", CPU, ids=lambda r: r.name)
def test_every_method_renders_the_box_through_render(record):
    vevm, camera, tf = box_scene()
    rgba, depth = render(vevm, camera, tf, method=record.name)
    assert rgba.shape == (4, 4, 4) and rgba.dtype == np.float32 and depth.dtype == np.float32
    inner = np.zeros((4, 4), bool)
    inner[1:3, 1:3] = True
    np.testing.assert_allclose(rgba[inner], 0.75, atol=1e-5)  # white: colour = alpha
    assert not rgba[~inner].any()
    np.testing.assert_allclose(depth[inner], 0.9975, atol=1e-6)
    assert (depth[~inner] == 1e10).all()
    # render() is the record's renderer at the full level, with the volume's placement.
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    direct = record.render(vevm, camera, tf, g, mode="over", depth_in=None)
    np.testing.assert_array_equal(direct[0], rgba)
    np.testing.assert_array_equal(direct[1], depth)


@pytest.mark.parametrize("record", CPU, ids=lambda r: r.name)
def test_memory_estimate_covers_the_image_and_tables_are_counted(record):
    vevm, camera, tf = box_scene()
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    fresh = VolumeEVM.from_volume(phantoms.box((4, 4, 4), lo=(1, 1, 1), hi=(3, 3, 3)), 0.5)
    options = {"mode": "over"}
    before = _tables_to_build(record.name, fresh, camera, tf, g, options)
    needed = render_memory(record.name, fresh, camera, tf, g, options)
    assert isinstance(needed, int) and needed >= 16 * 20 + record.memory.fixed
    assert before >= 1  # a fresh VolumeEVM has nothing cached
    render(fresh, camera, tf, method=record.name)
    after = _tables_to_build(record.name, fresh, camera, tf, g, options)
    assert 0 <= after <= before
    assert render_memory(record.name, fresh, camera, tf, g, options) <= needed


@pytest.mark.parametrize("record", RECORDS, ids=lambda r: r.name)
def test_quality_scales_the_sampling_and_gives_only_the_methods_options(record):
    spacing = (0.5, 0.7, 1.0)
    low, high = (method_options(record.name, q, spacing, shading=True, jitter=True,
                                slices_per_voxel=2) for q in (1.0, 4.0))
    assert set(high) - {"level"} <= set(render_options(record.name))
    sampling = record.quality(4.0, 0.5)
    assert sampling and set(sampling) <= set(render_options(record.name))
    assert {k: high[k] for k in sampling} == sampling
    assert {k: high[k] for k in sampling} != {k: low[k] for k in sampling}


@pytest.mark.parametrize("record", [r for r in RECORDS if r.check_samples is not None],
                         ids=lambda r: r.name)
def test_sample_bound_names_the_option_to_change(record):
    vevm, _, _ = box_scene()
    options = dict(record.options)
    record.check_samples(vevm, 16, options)  # the box scene is far below the bound
    with pytest.raises(VolumeEVMError, match=r"^(step_mm|substeps): .* use (step_mm|substeps) "):
        record.check_samples(vevm, 10**12, options)


@pytest.mark.parametrize("record", CPU, ids=lambda r: r.name)
def test_label_maps_render_only_with_the_methods_that_say_so(record):
    vevm = VolumeEVM.from_array(np.pad(np.full((2, 2, 2), 2.0), 1), 0.5)
    _, camera, _ = box_scene()
    tf = TransferFunction.categorical({2: (1.0, 0.0, 0.0, 1.0)})
    if not record.categorical:
        with pytest.raises(VolumeEVMError, match=f"^method: {record.name!r} interpolates"):
            render(vevm, camera, tf, method=record.name)
        return
    rgba, _ = render(vevm, camera, tf, method=record.name)
    assert rgba[1:3, 1:3, 3].min() > 0.5 and rgba[1:3, 1:3, 1:3].max() == 0.0
