"""The GPU method (``blender/gpu_draw.py``) against the NumPy reference, never golden images:
the box chord law and Gaussian blobs in closed form, the CT head within the CPU ray caster's
bounds at the same step, skipping on and off identical, the early-termination bound,
``depth_in``, the region's boundary policy in every mode, and the GPU state put back.

The images come from ``gpu_runner.py``, run once per test session in a Blender process of its
own with this interpreter (so each bpy line renders its own). Without a GPU context the tests
skip; with ``VOLUMEEVM_REQUIRE_GPU=1`` (CI) that is a failure.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import gpu_cases
from volumeevm_addon import TransferFunction, VolumeEVM, grid_to_world, phantoms, render
from volumeevm_addon.metrics import rmse
from volumeevm_addon.rendering import (
    BACKGROUND_DEPTH,
    axial_from_window,
    camera_from_viewport,
    composite_over,
)

RUNNER = Path(__file__).resolve().parent / "gpu_runner.py"
REQUIRE = "VOLUMEEVM_REQUIRE_GPU"


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, data_dir):
    """The runner's images and report."""
    out = tmp_path_factory.mktemp("gpu") / "gpu.npz"
    run = subprocess.run([sys.executable, str(RUNNER), str(out), str(data_dir)],
                         capture_output=True, text=True, timeout=1200)
    if run.returncode != 0 or not out.exists():
        pytest.fail(f"the GPU runner failed (exit {run.returncode}):\n{run.stderr[-4000:]}")
    with np.load(out) as data:
        arrays = {key: data[key] for key in data.files}
    meta = json.loads(str(arrays.pop("meta")))
    meta["vevm"] = out.with_suffix(".vevm")
    if not meta["context"]:
        message = f"no GPU context on bpy {meta['bpy']}: {meta['reason']}"
        if os.environ.get(REQUIRE) == "1":
            pytest.fail(f"{message} ({REQUIRE}=1)")
        pytest.skip(message)
    return arrays, meta


@pytest.fixture
def gpu(rendered):
    """``gpu(name)``: the GPU's (rgba, depth) for a case, failing with the runner's error."""
    arrays, meta = rendered

    def images(name):
        if name in meta["errors"]:
            pytest.fail(f"{name} on the GPU:\n{meta['errors'][name]}")
        return arrays[f"{name}_rgba"], arrays[f"{name}_depth"]

    return images


def reference(name, data_dir, **overrides):
    """The reference render of a case (its step: the reference's own, unless ``overrides``)."""
    vevm, cam, tf, options = gpu_cases.case(name, data_dir)
    keep = {k: options[k] for k in ("mode", "depth_in", "xray_scale", "xray_offset", "shading")
            if k in options}
    return render(vevm, cam, tf, method="reference", **keep, **overrides)


def drawn(rgba, least=0.5):
    """Something was drawn: the 4.5 driver once dropped a draw silently."""
    assert rgba[..., 3].max() > least and (rgba[..., 3] == 0).any()


# ---------------------------------------------------------------------------- closed forms
@pytest.mark.parametrize("name", ["box_ortho", "box_persp"])
def test_box_chord_law(gpu, name, data_dir):
    """A homogeneous box at a coarse step (0.45 mm, anisotropic voxels): ``1 - (1 - a)^L`` for
    the exact chord, since each part counts only its length inside the region; the depth is
    where the ray enters the box."""
    rgba, depth = gpu(name)
    drawn(rgba)
    vevm, cam, _, _ = gpu_cases.case(name, data_dir)
    g = grid_to_world(vevm.spacing, vevm.origin)
    chords = phantoms.box_chords_mm(cam, g, gpu_cases.BOX["lo"], gpu_cases.BOX["hi"])
    alpha = 1 - (1 - gpu_cases.BOX_ALPHA) ** chords
    np.testing.assert_allclose(rgba[..., 3], alpha, atol=2e-5)  # measured 3e-6
    np.testing.assert_allclose(rgba[..., 1], 0.6 * rgba[..., 3], atol=1e-6)
    _, ref_depth = reference(name, data_dir)
    np.testing.assert_array_equal(depth < BACKGROUND_DEPTH, ref_depth < BACKGROUND_DEPTH)
    seen = depth < BACKGROUND_DEPTH
    np.testing.assert_allclose(depth[seen], ref_depth[seen], rtol=1e-6)


@pytest.mark.parametrize("name", ["blobs_ortho", "blobs_persp"])
def test_blobs_closed_form(gpu, name, data_dir):
    """The reference's own bounds against the continuous closed form (test_phantoms), and
    close to the reference itself."""
    rgba, _ = gpu(name)
    drawn(rgba, 0.85)
    vevm, cam, _, _ = gpu_cases.case(name, data_dir)
    g = grid_to_world(vevm.spacing, vevm.origin)
    blob = gpu_cases.BLOB
    alpha = -np.expm1(-phantoms.blobs_optical_depth(cam, g, vevm.spacing, blob["centres"],
                                                    blob["sigmas"], blob["amplitudes"],
                                                    gpu_cases.BLOB_K))
    err = rgba[..., 3] - alpha
    assert np.sqrt(np.mean(err**2)) <= 0.0025 and np.abs(err).max() <= 0.01
    ref, _ = reference(name, data_dir)
    assert rmse(rgba, ref) < 1e-4  # measured 2e-5


# ---------------------------------------------------------------------------- real volume
@pytest.mark.parametrize("name", ["head_ortho", "head_persp"])
def test_ct_head_within_the_ray_casters_bounds(gpu, name, data_dir):
    """The CT head (bone), default step (half a voxel): the CPU ray caster's bounds of
    test_raycast (mean, 99th percentile, worst), no more than 1.2 times its RMSE at the same
    step; silhouette and depth of the region's surface as the reference's."""
    rgba, depth = gpu(name)
    drawn(rgba)
    vevm, cam, tf, options = gpu_cases.case(name, data_dir)
    ref, ref_depth = reference(name, data_dir)
    err = np.abs(rgba - ref).max(axis=-1)
    assert err.mean() < 0.001 and np.percentile(err, 99) < 0.02 and err.max() < 0.1
    cpu, _ = render(vevm, cam, tf, method="raycast", **options)
    assert rmse(rgba, ref) <= 1.2 * rmse(cpu, ref) + 1e-5
    np.testing.assert_array_equal(depth < BACKGROUND_DEPTH, ref_depth < BACKGROUND_DEPTH)
    seen = depth < BACKGROUND_DEPTH
    assert np.percentile(np.abs(depth - ref_depth)[seen], 99) < 1e-6


@pytest.mark.parametrize("name", ["labels_ortho", "labels_persp", "labels_liver_ortho",
                                  "labels_liver_persp"])
def test_label_maps_within_the_ray_casters_bounds(gpu, name, data_dir):
    """A categorical transfer function (label -> colour): the nearest voxel's label, the CPU
    ray caster's rule, no more than 1.5 times its RMSE to the reference and within its bounds
    of test_categorical_render (mean 0.015 on the phantom: its samples lie elsewhere along the
    rays, measured 0.0100 in perspective); red 1 beside blue 3 never shows green (an invented
    label 2)."""
    rgba, _ = gpu(name)
    assert rgba[..., 3].max() > 0.3  # drawn (the perspective view of the phantom is all volume)
    vevm, cam, tf, options = gpu_cases.case(name, data_dir)
    cpu, _ = render(vevm, cam, tf, method="raycast", **options)
    ref, _ = reference(name, data_dir)
    assert rmse(rgba, ref) <= 1.5 * rmse(cpu, ref) + 1e-5
    err = np.abs(rgba - ref).max(axis=-1)
    if "_liver" in name:
        assert err.mean() < 0.002 and np.percentile(err, 99) < 0.05 and err.max() < 0.2
    else:
        assert err.mean() < 0.015 and np.percentile(err, 99) < 0.15 and err.max() < 0.3
        assert rgba[..., 1].max() == 0.0 and rgba[..., 2].max() > 0.3


def test_skipping_changes_nothing(gpu):
    """Empty-space skipping leaps only over samples that add exact zeros."""
    rgba, depth = gpu("head_persp")
    dense_rgba, dense_depth = gpu("head_persp_noskip")
    drawn(rgba)
    np.testing.assert_array_equal(rgba, dense_rgba)
    np.testing.assert_array_equal(depth, dense_depth)


def test_early_termination_bound(gpu):
    """Stopping at 0.99 opacity changes a pixel by at most 0.01, and only pixels that reach it."""
    full, full_depth = gpu("head_persp")
    term, term_depth = gpu("head_persp_term")
    drawn(term)
    assert np.abs(term - full).max() <= 0.01 + 1e-6
    below = full[..., 3] < 0.985
    np.testing.assert_array_equal(term[below], full[below])
    assert (term[~below] != full[~below]).any()
    np.testing.assert_array_equal(term_depth, full_depth)


def test_depth_in_stops_the_rays(gpu, data_dir):
    """A tilted plane's axial depth (a render's Z pass) cuts every ray, as in the reference."""
    rgba, depth = gpu("head_persp_depth")
    drawn(rgba, 0.3)
    ref, ref_depth = reference("head_persp_depth", data_dir)
    full, _ = gpu("head_persp")
    assert (full[..., 3] - rgba[..., 3]).max() > 0.3  # the plane hides part of the volume
    err = np.abs(rgba - ref).max(axis=-1)
    assert err.mean() < 0.001 and np.percentile(err, 99) < 0.02
    _, _, _, options = gpu_cases.case("head_persp_depth", data_dir)
    seen = depth < BACKGROUND_DEPTH
    assert (depth[seen] <= options["depth_in"][seen] + 1e-6).all()
    np.testing.assert_array_equal(seen, ref_depth < BACKGROUND_DEPTH)


@pytest.mark.parametrize("name", ["head_persp_xray", "head_persp_mip"])
def test_xray_and_mip_on_the_head(gpu, name, data_dir):
    """The CPU ray caster's bounds (test_raycast's MIP bounds; X-ray: measured mean 2e-4,
    99th percentile 1.6e-3): MIP also evaluates each part's two ends, as it does."""
    rgba, depth = gpu(name)
    drawn(rgba, 0.3)
    ref, ref_depth = reference(name, data_dir)
    err = np.abs(rgba - ref).max(axis=-1)
    assert err.mean() < 0.005 and np.percentile(err, 99) < 0.03
    assert ((depth < BACKGROUND_DEPTH) != (ref_depth < BACKGROUND_DEPTH)).sum() <= 5


# ---------------------------------------------------------------------------- region policy
@pytest.mark.parametrize("name", ["irregular_over_ortho", "irregular_under_ortho",
                                  "irregular_xray_persp", "irregular_mip_persp"])
def test_region_boundary_policy(gpu, name, data_dir):
    """Random densities in a random region: the renormalised interpolation over region voxels
    and the region's cells placed exactly, in every mode (a 0.2 mm step)."""
    rgba, depth = gpu(name)
    drawn(rgba, 0.3)
    ref, ref_depth = reference(name, data_dir)
    assert rmse(rgba, ref) < (0.02 if "mip" in name else 2e-3)  # measured 0.0096, 6e-4
    seen = (depth < BACKGROUND_DEPTH) & (ref_depth < BACKGROUND_DEPTH)
    assert ((depth < BACKGROUND_DEPTH) != (ref_depth < BACKGROUND_DEPTH)).sum() <= 3
    # The region's cells are placed exactly; MIP's maximum is sampled (half a step: 1e-4).
    assert np.median(np.abs(depth - ref_depth)[seen]) < (1e-4 if "mip" in name else 1e-6)


# ---------------------------------------------------------------------------- shading
def test_shaded_ct_head_within_the_ray_casters_bounds(gpu, data_dir):
    """Shading on the CT head: the CPU methods' gradients, headlight and fade; within the CPU
    ray caster's error against the reference at the same step, and visibly lit."""
    rgba, depth = gpu("head_persp_shaded")
    drawn(rgba)
    plain, plain_depth = gpu("head_persp")
    assert np.abs(rgba - plain)[..., :3].mean() > 0.02
    np.testing.assert_array_equal(depth, plain_depth)
    vevm, cam, tf, options = gpu_cases.case("head_persp_shaded", data_dir)
    ref, _ = reference("head_persp_shaded", data_dir)
    cpu, _ = render(vevm, cam, tf, method="raycast", **options)
    assert rmse(rgba, ref) <= 1.2 * rmse(cpu, ref) + 1e-5  # measured 4.4e-3 and 4.2e-3


def test_shaded_region_boundary_policy(gpu, data_dir):
    """Shading on random densities in a random region: the gradients over region voxels only,
    interpolated over them, as the reference lights them."""
    rgba, _ = gpu("irregular_over_shaded_ortho")
    drawn(rgba, 0.3)
    plain, _ = gpu("irregular_over_ortho")
    assert np.abs(rgba - plain)[..., :3].mean() > 0.01
    ref, _ = reference("irregular_over_shaded_ortho", data_dir)
    assert rmse(rgba, ref) < 2e-3  # measured 9.5e-4 (the CPU ray caster's 9.3e-4)


def test_under_is_over(gpu):
    over, _ = gpu("irregular_over_ortho")
    under, _ = gpu("irregular_under_ortho")
    np.testing.assert_allclose(under, over, atol=1e-6)


def test_gpu_state_restored(rendered):
    assert rendered[1]["state_restored"]


def test_a_volume_too_large_for_the_gpu_is_refused(rendered):
    assert rendered[1]["too_large"].startswith("vevm: the GPU cannot hold a 16385x1x1 RG32F")


def test_a_volume_too_large_for_the_gpu_is_drawn_from_a_level_that_fits(rendered):
    """A box longer than the GPU's 3D textures, asked for at its full level: drawn from a
    coarser level, as the CPU ray caster renders that level."""
    arrays, meta = rendered
    if "long_box" in meta["errors"]:
        pytest.fail(f"the long box on the GPU:\n{meta['errors']['long_box']}")
    level = meta["long_box_level"]
    assert level > 1
    vevm, cam, tf, options = gpu_cases.long_box()
    drawn(arrays["long_box_rgba"])
    cpu, _ = render(vevm, cam, tf, method="raycast", **{**options, "level": level})
    assert rmse(arrays["long_box_rgba"], cpu) < 1e-3


# ---------------------------------------------------------------------------- render job
@pytest.fixture
def job(rendered):
    """``job(key)``: an array of Render VolumeEVM's results in the runner's scene
    (``scene_<what>_<method>``; the scene pass: ``scene_depth_in``, ``scene_colour_in``)."""
    arrays, meta = rendered
    if "scene" in meta["errors"]:
        pytest.fail(f"Render VolumeEVM in the runner:\n{meta['errors']['scene']}")
    return lambda key: arrays[f"scene_{key}"]


def test_render_job_with_the_gpu_method(job):
    """Render VolumeEVM with the method "gpu" gives the CPU ray caster's outputs at the same
    step: premultiplied RGBA within its error, the same axial depth, rays stopped at the
    scene's Z pass (a plane hides part of the skull), the same composite rule."""
    gpu_rgba, cpu_rgba = job("dvr_rgba_gpu"), job("dvr_rgba_raycast")
    drawn(gpu_rgba)
    assert rmse(gpu_rgba, cpu_rgba) < 1e-4  # measured 1.4e-6
    gpu_depth, cpu_depth = job("dvr_depth_gpu"), job("dvr_depth_raycast")
    np.testing.assert_array_equal(gpu_depth < BACKGROUND_DEPTH, cpu_depth < BACKGROUND_DEPTH)
    seen = gpu_depth < BACKGROUND_DEPTH
    assert np.median(np.abs(gpu_depth - cpu_depth)[seen]) < 1e-6
    covered = job("depth_in") < BACKGROUND_DEPTH
    assert 0.1 < covered.mean() < 0.9
    assert not gpu_rgba[covered].any() and (gpu_rgba[~covered][..., 3] > 0.5).any()
    assert (gpu_depth[seen] <= job("depth_in")[seen]).all()
    behind = job("colour_in")
    np.testing.assert_allclose(job("rgba_gpu"), gpu_rgba + (1 - gpu_rgba[..., 3:4]) * behind,
                               atol=1e-6)
    np.testing.assert_array_equal(job("depth_gpu"), np.where(seen, gpu_depth, job("depth_in")))


def test_render_job_falls_back_to_the_cpu(job, rendered):
    """Without a GPU context the method "gpu" renders with the CPU ray caster and says so."""
    notes = rendered[1]["scene_notes"]
    assert notes["gpu"] == "" and notes["raycast"] == ""
    assert "no GPU context" in notes["fallback"] and "ray casting" in notes["fallback"]
    np.testing.assert_array_equal(job("dvr_rgba_fallback"), job("dvr_rgba_raycast"))
    np.testing.assert_array_equal(job("dvr_depth_fallback"), job("dvr_depth_raycast"))


# ---------------------------------------------------------------------------- viewport
def test_viewport_draw_over_solid_equals_the_reference_composite(job, rendered):
    """The viewport's drawing over Blender's own Solid drawing (offscreen ``draw_view3d``, the
    scene camera's matrices, overlays off): its depth buffer stops the rays (the plane hides
    part of the skull, as the render's Z pass does) and the premultiplied DVR goes over the
    Solid colour: the reference composite (measured RMSE 1e-6)."""
    arrays, meta = rendered
    solid, window = arrays["viewport_solid"], arrays["viewport_window_depth"]
    h, w = window.shape
    camera = camera_from_viewport(arrays["viewport_projection"], arrays["viewport_view"], w, h)
    depth_in = axial_from_window(window, camera)
    seen = depth_in < BACKGROUND_DEPTH
    np.testing.assert_array_equal(seen, job("depth_in") < BACKGROUND_DEPTH)
    np.testing.assert_allclose(depth_in[seen], job("depth_in")[seen], rtol=1e-5)
    ref, _ = render(VolumeEVM.load(meta["vevm"]), camera, TransferFunction(gpu_cases.SKULL_TF),
                    method="reference", depth_in=depth_in,
                    matrix_world=arrays["viewport_matrix_world"])
    drawn(ref)
    composite = arrays["viewport_composite"]
    assert np.abs(composite - solid).max() > 0.3  # the volume was drawn
    assert rmse(composite, composite_over(ref, solid)) < 1e-4


def test_viewport_colour_through_a_display_table(job, rendered):
    """With a display table (here the sRGB one) the straight colour goes through it and into
    the display-linear space of the viewport's overlay merge (^2.2), premultiplied again;
    opacity unchanged. The table's cube-root lattice keeps the sRGB curve within 0.3 levels."""
    linear, shown = rendered[0]["viewport_alone_linear"], rendered[0]["viewport_alone_srgb"]
    drawn(linear)
    alpha = linear[..., 3:]
    np.testing.assert_array_equal(shown[..., 3:], alpha)
    straight = np.clip(linear[..., :3] / np.where(alpha > 0, alpha, 1), 0, 1)
    encoded = np.where(straight <= 0.0031308, 12.92 * straight,
                       1.055 * straight ** (1 / 2.4) - 0.055)
    got = (shown[..., :3] / np.where(alpha > 0, alpha, 1)) ** (1 / 2.2)
    seen = np.broadcast_to(alpha > 0, got.shape)
    assert np.abs(got - encoded)[seen].max() < 0.4 / 255  # measured 0.27 / 255
    assert (shown[..., :3] != linear[..., :3]).any()


# ---------------------------------------------------------------------------- viewport colour
def _srgb_decode(raw):
    """Linear values of 8-bit sRGB-encoded bytes (how the GPU reads an SRGB8_A8 texture)."""
    x = raw / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _over_black(premultiplied_linear):
    """Blender's display pass on an overlay over a black scene: ``(0 + overlay)^(1/2.2)``."""
    return premultiplied_linear ** (1 / 2.2)


@pytest.fixture
def display(rendered):
    """``display(case)``: the viewport's pixel over a black scene and its alpha (from the raw
    overlay bytes), F12's pixel over black merged as Blender merges overlays, and F12's alpha
    (from the saved PNG), as 8-bit levels."""
    arrays, meta = rendered
    if "display" in meta["errors"]:
        pytest.fail(f"the viewport's colours in the runner:\n{meta['errors']['display']}")

    def pixels(case, png_case=None):
        raw = arrays[f"display_{case}_overlay"].astype(np.float64)
        png = arrays[f"display_{png_case or case}_png"].astype(np.float64)
        viewport = _over_black(_srgb_decode(raw[..., :3])) * 255
        f12 = _over_black(png[..., 3:] * png[..., :3] ** 2.2) * 255
        return viewport, raw[..., 3], f12, png[..., 3] * 255

    return pixels


VIEW_CASES = ("standard", "filmic", "agx", "agx_exposed")


@pytest.mark.parametrize("case", VIEW_CASES)
def test_viewport_shows_what_f12_saves(display, case):
    """The CT head (skin and bone, shaded, transparent film): the viewport's drawing into an
    8-bit sRGB texture, as Blender's overlay, merged over a black scene as Blender's display
    pass merges it, against F12's PNG (the render job's image saved through the scene's colour
    management) under Standard, Filmic, AgX and AgX with exposure 0.7 and gamma 1.3: within 2
    levels of 255 everywhere, 1 on average (measured 1.23 and 0.6 on both bpy lines), the same
    opacity within 3 levels (measured 2)."""
    viewport, alpha, f12, f12_alpha = display(case)
    seen = (alpha > 0) | (f12_alpha > 0)
    assert seen.mean() > 0.2
    err = np.abs(viewport - f12).max(axis=-1)[seen]
    assert err.max() <= 2.0 and err.mean() <= 1.0
    assert np.abs(alpha - f12_alpha).max() <= 3.0


def test_view_transforms_change_what_the_viewport_shows(display, rendered):
    """The cases differ (AgX from Standard by about 58 levels at most): a viewport without the
    scene's view transform would fail the test above; each new setting needed a new table."""
    standard, _, standard_f12, _ = display("standard")
    for case in VIEW_CASES[1:]:
        viewport, _, f12, _ = display(case)
        assert np.abs(f12 - standard_f12).max() > 20 and np.abs(viewport - standard).max() > 20
    meta = rendered[1]
    assert not any(meta[f"display_{case}_current_before"] for case in VIEW_CASES)
    assert all(seconds < 5.0 for seconds in meta["display_bake_seconds"].values())


def test_a_view_transform_that_cannot_be_baked_falls_back_to_standard(display, rendered):
    """A bake that fails (no writable temporary folder): the viewport draws with the sRGB table,
    what F12 saves under Standard, not AgX's, and the sidebar says why."""
    meta = rendered[1]
    assert meta["display_refreshed_without_tmp"] is False
    text = meta["display_colour_problem"]
    assert text.startswith("Viewport colours as 'Standard':")
    assert "'AgX' could not be baked" in text and "No such file or directory" in text
    viewport, alpha, standard_f12, f12_alpha = display("fallback", "standard")
    seen = (alpha > 0) | (f12_alpha > 0)
    assert np.abs(viewport - standard_f12).max(axis=-1)[seen].max() <= 2.0
    _, _, agx_f12, _ = display("fallback", "agx")
    assert np.abs(viewport - agx_f12).max() > 20


def test_a_moving_view_rests_after_a_quarter_second():
    """:class:`ViewMotion` fed with times and signatures: a view first seen rests; a changed
    signature moves it; it rests again ``rest`` seconds after its last change; views are
    apart; ``clear`` forgets them."""
    motion = _viewport().ViewMotion(rest=0.25)
    still, turned = np.eye(4).tobytes(), np.diag([1.0, -1.0, 1.0, 1.0]).tobytes()
    assert motion.observe("a", still, 10.0) == 0.0
    assert motion.observe("a", still, 10.1) == 0.0  # a redraw of the same view
    assert motion.observe("a", turned, 10.2) == 0.25
    assert motion.observe("a", turned, 10.3) == pytest.approx(0.15)  # still settling
    assert motion.observe("b", turned, 10.3) == 0.0  # another region
    assert motion.observe("a", still, 10.4) == 0.25  # moved again: the rest starts over
    assert motion.observe("a", still, 10.6) == pytest.approx(0.05)
    assert motion.observe("a", still, 10.65) == 0.0
    assert motion.observe("a", still, 11.0) == 0.0
    motion.clear()
    assert motion.observe("a", turned, 11.1) == 0.0


def test_moving_options_and_level_texts():
    module = _viewport()
    options = {"step_mm": 0.4, "termination": 0.99, "level": "auto"}
    assert module.draw_options(options, False) is options
    assert module.draw_options(options, True) == {**options, "step_mm": 0.4 * module.MOVING_STEP,
                                                  "pixel": module.MOVING_PIXEL}
    assert module.MOVING_STEP > 1.0 and module.MOVING_PIXEL > 1
    level_text = module.gpu_draw.level_text
    assert level_text(1) == "" and level_text(2) == "level 2 (2\u00d7 coarser voxels)"


@pytest.mark.parametrize("size", [1, 2, 3, 5, 8, 1280, 1281])
def test_depth_blocks_are_the_pixels_the_stretch_shows(size):
    """While moving, each coarse ray stops at the nearest depth of exactly the pixels the stretch
    shader shows it on (pixel ``x`` shows ``floor((x + 1/2) n / size)``), odd sizes too."""
    n = -(-size // 2)
    starts = _viewport().block_starts(size, n)
    shown = np.floor((np.arange(size) + 0.5) * n / size).astype(np.int64)
    np.testing.assert_array_equal(starts, [np.flatnonzero(shown == i)[0] for i in range(n)])


def test_the_moving_frame_is_cheaper_and_close(gpu, rendered, data_dir):
    """The viewport's drawing while the view moves: a ray per 2×2 pixels (each block shows its
    ray) with twice the step, close to the reference at that coarser image (measured RMSE
    0.004); at rest, to the reference at the full image (0.0008)."""
    arrays, meta = rendered
    options = meta["moving"]
    assert options["moving"] == {**options["resting"], "pixel": 2,
                                 "step_mm": 2 * options["resting"]["step_mm"]}
    assert options["levels"] == [1, 1, 2]
    vevm, cam, tf, _ = gpu_cases.case("head_persp", data_dir)
    resting, moving = arrays["resting_rgba"], arrays["moving_rgba"]
    drawn(moving)
    assert rmse(resting, render(vevm, cam, tf, method="reference")[0]) < 0.005
    for dy in (0, 1):
        for dx in (0, 1):
            np.testing.assert_array_equal(moving[dy::2, dx::2], moving[::2, ::2])
    h, w = cam.shape
    coarse = camera_from_viewport(cam.matrix_projection(), np.linalg.inv(cam.matrix_world),
                                  w // 2, h // 2)
    assert rmse(moving[::2, ::2], render(vevm, coarse, tf, method="reference")[0]) < 0.01


def test_the_gpu_render_says_which_level_it_drew(job, rendered):
    notes = rendered[1]["scene_notes"]
    assert notes["level"] == "rendered from level 2 (2\u00d7 coarser voxels)"
    drawn(job("dvr_rgba_level"))


def test_viewport_handler_draws_coarser_while_the_view_moves(rendered):
    """The handler's drawing with the Render settings: full quality when first seen; the view
    turned: a ray per 2×2 pixels, twice the step and a timer set to redraw once it rests;
    unchanged after a rest: full quality again; far away: level Auto draws a coarser level and
    the sidebar says so. Every draw shows the skull."""
    arrays, meta = rendered
    if "scene" in meta["errors"]:
        pytest.fail(f"the viewport in the runner:\n{meta['errors']['scene']}")
    (step, pixel, timer, level), moved, rested, far = arrays["handler_trace"]
    assert (pixel, timer, level) == (1, 0, 1)
    assert moved[0] == pytest.approx(2 * step) and moved[1] == 2 and moved[2] == 1
    assert rested[0] == step and rested[1] == 1 and rested[3] == 1
    assert far[3] > 1
    assert str(arrays["handler_level_text"]) == (f"Showing level {int(far[3])} "
                                                 f"({int(far[3])}\u00d7 coarser voxels)")
    for alpha in arrays["handler_alpha"]:
        assert alpha.max() > 0.5 and (alpha == 0).any()


def _viewport():
    """``blender/gpu_viewport.py`` imported as part of the extension (no GPU needed)."""
    import importlib

    from blender_helpers import addon

    return importlib.import_module(f"{addon().__name__}.blender.gpu_viewport")


def test_viewport_handler_and_textures_follow_registration_and_file_loads(job, rendered):
    assert rendered[1]["viewport_handlers"] == {"registered": True, "textures kept": True,
                                                "freed on load": True, "removed": True}
