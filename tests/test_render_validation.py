"""render(), the image writers and the mesh refuse bad input and work that would not fit, with a
VolumeEVMError naming the parameter (issue 9, sections 3 and 4)."""

import re
import tracemalloc

import numpy as np
import pytest

from render_helpers import camera, const_tf
from skips import skip_unless_ci
from volumeevm_addon import (
    EVM,
    METHODS,
    Camera,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    grid_to_world,
    render,
    write_exr,
    write_png,
)
from volumeevm_addon._memory import format_bytes
from volumeevm_addon.rendering import openexr_module
from volumeevm_addon.rendering._ray_march import BLOCK_VOXELS
from volumeevm_addon.rendering._raycast import _Blocks, _SamplingTable, table_bytes
from volumeevm_addon.rendering._render import check_samples, render_memory


@pytest.fixture(scope="module")
def scene():
    """A small random VolumeEVM, an orthographic 8x6 camera looking at it, a transfer function."""
    rng = np.random.default_rng(9)
    vevm = VolumeEVM.from_array(rng.random((6, 7, 5)), 0.3, spacing=(1.0, 1.5, 2.0))
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    return vevm, camera("ORTHO", g, vevm, (0.0, -0.05, 0.02), 0.02, res=(8, 6)), const_tf(0.3)


def test_bad_method_and_mode(scene):
    vevm, cam, tf = scene
    with pytest.raises(VolumeEVMError, match="^method: one of .*'ray_march'"):
        render(vevm, cam, tf, method="ray_march")
    for method in METHODS:
        with pytest.raises(VolumeEVMError, match="^mode: one of .*'average'"):
            render(vevm, cam, tf, method=method, mode="average")


def test_bad_arguments_name_the_parameter(scene):
    vevm, cam, tf = scene
    with pytest.raises(VolumeEVMError, match="^vevm: expected a VolumeEVM, got str"):
        render("head.vevm", cam, tf)
    with pytest.raises(VolumeEVMError, match="^camera: expected a Camera, got dict"):
        render(vevm, {"lens": 50}, tf)
    with pytest.raises(VolumeEVMError, match="^matrix_world: expected an array of numbers"):
        render(vevm, cam, tf, matrix_world="identity")
    with pytest.raises(VolumeEVMError, match="^matrix_world: expected a finite affine 4x4"):
        render(vevm, cam, tf, matrix_world=np.zeros((4, 4)))
    with pytest.raises(VolumeEVMError, match="^depth_in: expected an array of numbers"):
        render(vevm, cam, tf, depth_in="far")


def test_unknown_option_stays_a_type_error(scene):
    vevm, cam, tf = scene
    with pytest.raises(TypeError, match="^step_mm: not an option of method 'shear_warp'"):
        render(vevm, cam, tf, method="shear_warp", step_mm=0.5)


@pytest.mark.parametrize("method, option, value", [
    ("raycast", "step_mm", -0.5),
    ("raycast", "step_mm", 0.0),
    ("raycast", "step_mm", float("nan")),
    ("raycast", "step_mm", float("inf")),
    ("raycast", "step_mm", "fine"),
    ("reference", "step_mm", "fine"),
    ("raycast_navigate", "step_mm", -1.0),
    ("raycast", "termination", 0.0),
    ("raycast", "termination", 1.5),
    ("splat", "termination", float("nan")),
    ("raycast", "block", 2.5),
    ("raycast", "block", "8"),
    ("raycast", "block", 0),
    ("raycast", "chunk_rays", float("inf")),
    ("raycast", "skip_empty", "yes"),
    ("shear_warp", "skip_empty", None),
    ("raycast", "jitter", 1),
    ("shear_warp", "slices_per_voxel", 0),
    ("shear_warp", "slices_per_voxel", 2.0),
    ("shear_warp", "lut_size", float("nan")),
    ("shear_warp", "intermediate_scale", float("nan")),
    ("shear_warp", "intermediate_scale", 0.0),
    ("splat", "substeps", 0),
    ("splat", "substeps", True),
    ("splat", "max_footprint_px", float("inf")),
    ("splat", "blend", 1.0),
    ("reference", "chunk_rays", float("nan")),
    ("reference", "boundary", "wrap"),
])
def test_bad_option_values_name_the_option(scene, method, option, value):
    vevm, cam, tf = scene
    with pytest.raises(VolumeEVMError, match=f"^{option}"):
        render(vevm, cam, tf, method=method, **{option: value})


def test_good_options_still_render(scene):
    vevm, cam, tf = scene
    rgba, depth = render(vevm, cam, tf, method="raycast", step_mm=0.5, block=np.int64(4),
                         skip_empty=np.bool_(True), termination=1)
    # NumPy scalars and an int where a float is expected give the plain options' image.
    plain_rgba, plain_depth = render(vevm, cam, tf, method="raycast", step_mm=0.5, block=4,
                                     skip_empty=True, termination=1.0)
    assert (rgba[..., 3] > 0).any()
    np.testing.assert_array_equal(rgba, plain_rgba)
    np.testing.assert_array_equal(depth, plain_depth)


def test_huge_image_is_refused_before_allocating(scene, monkeypatch):
    vevm, _, tf = scene
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "8G")
    m = np.eye(4)
    m[:3, 3] = (0.0, 0.0, 1.0)
    huge = Camera.orthographic(m, 0.02, resolution_x=100000, resolution_y=100000)
    with pytest.raises(VolumeEVMError, match=r"^camera: a 100000x100000 image needs about "
                                             r"186\.3 GiB .* only 8\.0 GiB is available; lower"):
        render(vevm, huge, tf)


@pytest.mark.parametrize("method", ["raycast", "raycast_navigate", "reference"])
def test_tiny_step_is_refused_with_a_usable_step(scene, method):
    vevm, cam, tf = scene
    with pytest.raises(VolumeEVMError, match=r"^step_mm: a step of 1e-09 mm would take about "
                                             r".* use step_mm >= ") as error:
        render(vevm, cam, tf, method=method, step_mm=1e-9)
    smallest = float(str(error.value).split("step_mm >= ")[1].split()[0])
    # The step the message proposes (rounded to 3 digits, so 1% above it) passes the bound.
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    check_samples(method, vevm, cam, g, {"step_mm": smallest * 1.01})
    with pytest.raises(VolumeEVMError, match="^step_mm"):
        check_samples(method, vevm, cam, g, {"step_mm": smallest * 0.99})


def test_too_many_substeps_are_refused(scene):
    vevm, cam, tf = scene
    with pytest.raises(VolumeEVMError, match=r"^substeps: 10000000000 sub-slabs .* use substeps "
                                             r"<= \d+"):
        render(vevm, cam, tf, method="splat", substeps=10**10)


def test_sample_bound_counts_covered_pixels_only(scene):
    """The bound counts the pixels the volume covers: a step refused in a frame the volume
    fills is accepted when the volume covers a few pixels of the same frame."""
    vevm, _, _ = scene
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    step = {"step_mm": 1e-5}
    far = camera("ORTHO", g, vevm, (0.0, -0.05, 0.02), 20.0, res=(2000, 2000))
    check_samples("raycast", vevm, far, g, step)  # a 2x2-pixel footprint: 4 x 1.3e6 samples
    near = camera("ORTHO", g, vevm, (0.0, -0.05, 0.02), 0.02, res=(2000, 2000))
    with pytest.raises(VolumeEVMError, match="^step_mm: a step of 1e-05 mm"):
        check_samples("raycast", vevm, near, g, step)


@pytest.mark.parametrize("method", METHODS)
def test_small_budget_refuses_render_naming_what_and_how_much(scene, method, monkeypatch):
    vevm, cam, tf = scene
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    needed = render_memory(method, vevm, cam, tf, g, {"mode": "over"})
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", str(needed - 1))
    with pytest.raises(VolumeEVMError, match=(
            rf"^render: rendering 6x7x5 voxels at 8x6 pixels \({method}\) needs about "
            rf"{re.escape(format_bytes(needed))} of memory but only "
            rf"{re.escape(format_bytes(needed - 1))} is available; "
            rf"{'the reference renders' if method == 'reference' else 'render a coarser'}")):
        render(vevm, cam, tf, method=method)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", str(needed))
    rgba, _ = render(vevm, cam, tf, method=method)
    assert (rgba[..., 3] > 0).any()


def test_generous_budget_renders_as_without_one(scene, monkeypatch):
    vevm, cam, tf = scene
    want = render(vevm, cam, tf, method="raycast")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4G")
    got = render(vevm, cam, tf, method="raycast")
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_render_memory_grows_with_image_and_grid(scene):
    vevm, cam, tf = scene
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    big = camera("ORTHO", g, vevm, (0.0, -0.05, 0.02), 0.02, res=(16, 12))
    over = {"mode": "over"}
    for method in METHODS:
        small = render_memory(method, vevm, cam, tf, g, over)
        assert render_memory(method, vevm, big, tf, g, over) > small
    for method in ("raycast", "shear_warp", "reference"):  # gradient tables when shading
        assert render_memory(method, vevm, cam, tf, g, {**over, "shading": True}) > \
            render_memory(method, vevm, cam, tf, g, over)


def _blob(n):
    """A smooth ellipsoidal density (positive inside), as real data: a compact EVM."""
    x, y, z = np.indices((n, n, n)) - (n - 1) / 2
    return (n / 2 - np.sqrt(x * x + 1.3 * y * y + 0.8 * z * z)).astype(np.float32)


def _traced_peak(step):
    """``(result of step(), tracemalloc peak of the call in bytes)``."""
    tracemalloc.start()
    try:
        result = step()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("method", ["shear_warp", "splat", "raycast", "raycast_navigate"])
def test_warm_estimate_drops_cached_tables_and_covers_the_warm_peak(method, monkeypatch):
    """Once a render has cached the method's tables on the VolumeEVM, the estimate of the
    same render no longer counts them: smaller than the cold one, still at least the measured
    peak of the warm render. A budget of the warm estimate renders the warm VolumeEVM (same
    image) and refuses a fresh one, whose tables would still have to be built."""
    spacing = (1.0, 1.5, 2.0)
    vevm = VolumeEVM.from_array(_blob(48), 0.0, spacing=spacing)
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    cam = camera("ORTHO", g, vevm, (0.3, -0.5, 0.2), 0.2, res=(64, 48))
    tf = const_tf(0.3)
    cold = render_memory(method, vevm, cam, tf, g, {"mode": "over"})
    want = render(vevm, cam, tf, method=method)
    assert (want[0][..., 3] > 0).any()
    warm = render_memory(method, vevm, cam, tf, g, {"mode": "over"})
    assert warm < cold
    got, peak = _traced_peak(lambda: render(vevm, cam, tf, method=method))
    assert peak <= warm
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", str(warm))
    np.testing.assert_array_equal(render(vevm, cam, tf, method=method)[0], want[0])
    fresh = VolumeEVM.from_array(_blob(48), 0.0, spacing=spacing)
    with pytest.raises(VolumeEVMError, match=rf"^render: rendering 48x48x48 voxels at 64x48 "
                                             rf"pixels \({method}\) needs about "):
        render(fresh, cam, tf, method=method)


def test_estimate_counts_the_tables_a_render_would_still_build():
    """Tables cached for one render do not make another one warm when it needs others: a
    different block size (ray casting), transfer function (shear-warp's classes), shading
    (gradients) or principal axis (splatting's sections) is estimated as cold."""
    vevm = VolumeEVM.from_array(_blob(24), 0.0)
    g = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)
    front = camera("ORTHO", g, vevm, (0.0, -1.0, 0.0), 0.1, res=(16, 16))
    side = camera("ORTHO", g, vevm, (1.0, 0.0, 0.0), 0.1, res=(16, 16))
    tf, other = const_tf(0.3), const_tf(0.5)
    over = {"mode": "over"}

    def estimate(method, cam=front, tf_=tf, **options):
        return render_memory(method, vevm, cam, tf_, g, {**over, **options})

    cold = {m: estimate(m) for m in ("raycast", "shear_warp", "splat")}
    cold_side, cold_block = estimate("splat", side), estimate("raycast", block=2)
    cold_shaded = estimate("shear_warp", shading=True)
    for method in cold:
        render(vevm, front, tf, method=method)
        assert estimate(method) < cold[method]
    assert estimate("raycast", block=2) == cold_block
    assert estimate("shear_warp", tf_=other) == cold["shear_warp"]
    assert estimate("shear_warp", shading=True) == cold_shaded
    assert estimate("splat", side) == cold_side


def test_ray_casting_tables_are_built_without_grid_sized_temporaries():
    """The block-sparse sampling table (written straight from the EVM's boxes) and the
    space-leaping blocks (ranges from the boxes too) cost about their own size and the EVM's
    boxes' (the estimate of the memory check covers it): no grid-sized array, not even the
    region mask, is made on the way."""
    vevm = VolumeEVM.from_array(_blob(64), 0.0)
    boxes = len(vevm.evm.boxes()[0])
    table, peak = _traced_peak(lambda: _SamplingTable(vevm))
    assert table.table.nbytes == 4 * BLOCK_VOXELS * int((table.index >= 0).sum())
    estimate = table_bytes(vevm, {"skip_empty": False}, navigate=False)
    assert peak <= estimate <= 1.5 * (table.table.nbytes + table.index.nbytes) + (256 << 10)
    blocks, peak = _traced_peak(lambda: _Blocks(vevm, 8))
    assert peak <= 10 * blocks.range_lo.size + 224 * boxes + (64 << 10)


def test_small_budget_refuses_mesh_naming_what_and_how_much(monkeypatch):
    rng = np.random.default_rng(3)
    evm = EVM.from_mask(rng.random((30, 30, 30)) < 0.5)
    vertices, polygons = evm.mesh()
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1M")
    with pytest.raises(VolumeEVMError, match=(
            r"^mesh: making the boundary mesh \(\d+ face runs perpendicular to axis x\) needs "
            r"about [\d.]+ MiB of memory but only 1\.0 MiB is available; build the VolumeEVM "
            r"with a higher threshold")):
        evm.mesh()
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1G")
    again_vertices, again_polygons = evm.mesh()
    np.testing.assert_array_equal(again_vertices, vertices)
    np.testing.assert_array_equal(again_polygons.indices, polygons.indices)


def test_mesh_checks_the_faces_not_only_the_vertices(monkeypatch):
    """A checkerboard has few extreme vertices but a face per voxel side: the rectangles' count
    drives the estimate, so a budget that fits the vertices many times over is refused."""
    checker = np.indices((24, 24, 24)).sum(axis=0) % 2 == 0
    evm = EVM.from_mask(checker)
    assert len(evm.vertices) < 500
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "2M")
    with pytest.raises(VolumeEVMError, match=r"^mesh: making the boundary mesh \(\d+ "):
        evm.mesh()


def test_empty_and_misshapen_images_are_refused(tmp_path):
    for shape in [(0, 0, 4), (0, 5, 4), (5, 0, 4)]:
        with pytest.raises(VolumeEVMError, match=r"^rgba: the image is empty \(shape "):
            write_png(tmp_path / "x.png", np.zeros(shape))
    for shape in [(4, 4), (4, 4, 3), (4, 4, 4, 1), ()]:
        with pytest.raises(VolumeEVMError, match=r"^rgba: expected \(H, W, 4\)"):
            write_png(tmp_path / "x.png", np.zeros(shape))
    with pytest.raises(VolumeEVMError, match="^rgba: expected an array of numbers"):
        write_png(tmp_path / "x.png", [["red"]])
    nan = np.zeros((2, 2, 4))
    nan[1, 1, 0] = np.nan
    with pytest.raises(VolumeEVMError, match="^rgba: 1 NaN values"):
        write_png(tmp_path / "x.png", nan)
    assert list(tmp_path.iterdir()) == []


def test_empty_exr_is_refused(tmp_path):
    if openexr_module() is None:
        skip_unless_ci("OpenEXR is not installed")
    with pytest.raises(VolumeEVMError, match=r"^rgba: the image is empty \(shape \(0, 0, 4\)\)"):
        write_exr(tmp_path / "x.exr", np.zeros((0, 0, 4)))
    with pytest.raises(VolumeEVMError, match=r"^rgba: expected \(H, W, 4\)"):
        write_exr(tmp_path / "x.exr", np.zeros((3, 4)))
    with pytest.raises(VolumeEVMError, match=r"^depth: expected shape \(3, 4\), got \(0, 4\)"):
        write_exr(tmp_path / "x.exr", np.zeros((3, 4, 4)), np.zeros((0, 4)))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("method", ["raycast", "splat", "shear_warp"])
def test_renderers_called_directly_check_depth_in(method):
    """The renderers share the depth_in check with render(): bad values are VolumeEVMErrors."""
    from volumeevm_addon.rendering import _raycast, _shear_warp, _splat

    vevm = VolumeEVM.from_array(np.pad(np.ones((4, 4, 4)), 2), 0.5)
    cam = Camera.look_at((4.0, -20.0, 4.0), (4.0, 4.0, 4.0), ortho_scale=12.0,
                         resolution_x=6, resolution_y=5)
    renderer = {"raycast": _raycast.render_raycast, "splat": _splat.render_splat,
                "shear_warp": _shear_warp.render_shear_warp}[method]
    tf = TransferFunction.preset("ct_bone")
    for bad, match in (("far", "expected an array of numbers, got str"),
                       (np.ones((4, 4)), r"shape \(4, 4\) differs from the image's \(5, 6\)"),
                       (np.full((5, 6), np.nan), "30 NaN values; use 1e10 for no geometry")):
        with pytest.raises(VolumeEVMError, match=f"^depth_in: {match}"):
            renderer(vevm, cam, tf, np.eye(4), depth_in=bad)
