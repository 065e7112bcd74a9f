"""What the renderers derive from a VolumeEVM lives in its cache (``vevm.cache``): counted by
``size_report()``, bounded by a budget (least recently used dropped first), clearable, and the
same cache the memory estimate looks in. Dropping entries never changes an image."""

import gc
import json
import threading
import time
import weakref

import numpy as np
import pytest

from volumeevm_addon import (
    Camera,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    grid_to_world,
    phantoms,
    render,
)
from volumeevm_addon.model import DerivedCache
from volumeevm_addon.model._cache import held_bytes
from volumeevm_addon.rendering._ray_march import BLOCK_VOXELS
from volumeevm_addon.rendering._render import _tables_to_build

CT_CROP = (slice(64, 192), slice(48, 176), slice(30, 80))  # 128 x 128 x 50 voxels of the CT head
BONE = TransferFunction.preset("ct_bone")
VIEWS = {  # camera offsets from the volume's centre (world, Blender units)
    "x": ((0.4, 0.1, 0.05), "ORTHO"),
    "y": ((0.1, 0.4, 0.2), "ORTHO"),
    "z": ((0.05, 0.1, 0.5), "ORTHO"),
    "diagonal": ((0.3, 0.3, 0.05), "ORTHO"),  # splatting blends two sheet families here
    "perspective": ((0.5, 0.2, 0.1), "PERSP"),
}
CASES = [  # (method, options) covering every kind of entry each method keeps
    ("shear_warp", {}),
    ("shear_warp", {"shading": True}),
    ("shear_warp", {"classification": "post", "mode": "under"}),
    ("shear_warp", {"mode": "mip"}),
    ("splat", {}),
    ("splat", {"mode": "xray", "xray_scale": 2e-4, "xray_offset": -1024.0}),
    ("raycast", {}),
    ("raycast", {"shading": True, "preintegrate": True}),
    ("raycast_navigate", {"step_mm": 2.0}),
]


@pytest.fixture(scope="module")
def head(data_dir):
    """A crop of the real CT head, region at 300 HU and above, and its grid-to-world matrix."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    array = np.ascontiguousarray(np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP])
    vevm = VolumeEVM.from_array(array, 300, spacing=meta["spacing_mm"], units="HU")
    return vevm, grid_to_world(vevm.spacing, vevm.origin, vevm.orientation)


def fresh(vevm):
    """The same VolumeEVM with an empty cache."""
    return VolumeEVM(vevm.evm, vevm.table(), shape=vevm.shape, spacing=vevm.spacing,
                     units=vevm.units, threshold=vevm.threshold)


def camera(vevm, g, view, res=(32, 24)):
    offset, kind = VIEWS[view]
    centre = g[:3, 3] + g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0)
    return Camera.look_at(centre + np.asarray(offset), centre, kind=kind, ortho_scale=0.2,
                          resolution_x=res[0], resolution_y=res[1], clip_start=1e-4)


def draw(vevm, g, view, method, options):
    """``render`` of ``view`` with ``method`` and ``options`` (``mode`` among them)."""
    options = dict(options)
    mode = options.pop("mode", "over")
    return render(vevm, camera(vevm, g, view), BONE, method=method, mode=mode, **options)


def entries_bytes(cache):
    """The bytes of the cache's entries, summed here entry by entry (each array once)."""
    seen = set()
    return sum(held_bytes(cache.get(key, None), seen) for key in cache.keys())


@pytest.mark.parametrize("method, options", CASES, ids=lambda c: str(c))
def test_renders_fill_the_cache_it_counts_and_clearing_changes_no_image(head, method, options):
    vevm = fresh(head[0])
    g = head[1]
    before = vevm.size_report()
    assert before["cache_bytes"] == 0
    needs = dict({"mode": "over"}, **options)
    assert _tables_to_build(method, vevm, camera(vevm, g, "x"), BONE, g, needs) == 1
    rgba, depth = draw(vevm, g, "x", method, options)
    report = vevm.size_report()
    # Everything the view needs is now in the cache, and the cache counts what it holds.
    assert _tables_to_build(method, vevm, camera(vevm, g, "x"), BONE, g, needs) == 0
    assert report["cache_bytes"] == vevm.cache.nbytes == entries_bytes(vevm.cache) > 0
    # The model itself is what it was: its keys keep their meaning.
    assert {k: report[k] for k in ("vertices_bytes", "dense_bytes")} == \
        {k: before[k] for k in ("vertices_bytes", "dense_bytes")}
    assert report["total_bytes"] == report["vertices_bytes"] + report["tables_bytes"]
    assert report["ratio"] == report["total_bytes"] / report["dense_bytes"]
    vevm.cache.clear()
    assert vevm.size_report()["cache_bytes"] == 0 and len(vevm.cache) == 0
    again = draw(vevm, g, "x", method, options)
    np.testing.assert_array_equal(again[0], rgba)
    np.testing.assert_array_equal(again[1], depth)


def test_the_sampling_table_is_counted(head):
    """Ray casting keeps a table over the stored blocks of the padded grid (the CT head's
    int16, in its own type) and their int32 index: the count includes both."""
    vevm = fresh(head[0])
    draw(vevm, head[1], "x", "raycast", {})
    table = vevm.cache.get(("raycast", "table"), lambda: None)
    stored = int((table.index >= 0).sum())
    assert vevm.table().dtype == table.table.dtype == np.int16
    assert stored > 0 and table.table.nbytes == 2 * BLOCK_VOXELS * stored
    assert vevm.size_report()["cache_bytes"] >= table.table.nbytes + table.index.nbytes


@pytest.mark.parametrize("method, options", CASES, ids=lambda c: str(c))
def test_a_small_budget_bounds_the_cache_and_changes_no_image(head, method, options):
    vevm, g = head
    views = ("x", "y", "perspective")
    unbounded = fresh(vevm)
    images = [draw(unbounded, g, view, method, options) for view in views]
    full = unbounded.cache.nbytes
    for budget in (full // 3, 0):
        bounded = fresh(vevm)
        bounded.cache.budget = budget
        for view, image in zip(views, images):
            got = draw(bounded, g, view, method, options)
            # An entry that grows while in use (splatting's culled voxels, filled a slice at a
            # time) is measured at the cache's next use.
            bounded.cache.get(("next use",), tuple)
            bounded.cache.discard(("next use",))
            assert bounded.cache.nbytes <= budget
            np.testing.assert_array_equal(got[0], image[0])
            np.testing.assert_array_equal(got[1], image[1])
        assert len(bounded.cache) < len(unbounded.cache)


def made_during(vevm, run):
    """The keys ``vevm.cache`` made entries for while ``run()`` ran."""
    made = []
    get = vevm.cache.get

    def recording(key, make):
        if key not in vevm.cache:
            made.append(key)
        return get(key, make)

    vevm.cache.get = recording
    try:
        run()
    finally:
        del vevm.cache.get
    return made


def is_table(key):
    """Entries the memory estimate counts (the grid tables), not the data range or culled
    voxels, which are small beside them."""
    return key[:2] not in (("raycast", "range"), ("splat", "kept"))


@pytest.mark.parametrize("method, options", CASES, ids=lambda c: str(c))
def test_the_memory_estimate_sees_the_cache_the_renderer_uses(head, method, options):
    """Before every render of a sequence (cold, repeated, another axis, perspective, back),
    the estimate's query says tables would be built exactly when the render builds some; after
    a render it says none would be."""
    vevm = fresh(head[0])
    g = head[1]
    options = dict(options)
    mode = options.pop("mode", "over")
    for view in ("x", "x", "y", "perspective", "diagonal", "z", "x"):
        cam = camera(vevm, g, view)

        def to_build():
            return _tables_to_build(method, vevm, cam, BONE, g, {"mode": mode, **options})

        expected = to_build()
        made = [key for key in made_during(vevm, lambda: render(
            vevm, cam, BONE, method=method, mode=mode, **options)) if is_table(key)]
        assert bool(expected) == bool(made), (view, expected, made)
        assert to_build() == 0, view


def test_transfer_functions_are_keyed_by_their_points_and_not_kept_alive(head):
    """Shear-warp keeps per-function classes under the function's control points: an equal
    function reuses them, and the cache holds no function (nor the tables it caches itself)."""
    vevm = fresh(head[0])
    g = head[1]
    cam = camera(vevm, g, "x")
    tf = TransferFunction(BONE.points.copy())
    first = render(vevm, cam, tf, method="shear_warp")
    alive = weakref.ref(tf)
    del tf
    gc.collect()
    assert alive() is None
    equal = TransferFunction(BONE.points.copy())
    assert _tables_to_build("shear_warp", vevm, cam, equal, g, {"mode": "over"}) == 0
    assert not made_during(vevm, lambda: render(vevm, cam, equal, method="shear_warp"))
    np.testing.assert_array_equal(render(vevm, cam, equal, method="shear_warp")[0], first[0])


def test_levels_are_kept_in_the_cache_and_counted(head):
    vevm = fresh(head[0])
    g = head[1]
    rgba, _ = render(vevm, camera(vevm, g, "x"), BONE, method="raycast", level=2)
    assert ("level", 2) in vevm.cache
    level = vevm.level(2)
    assert level.size_report()["cache_bytes"] > 0  # the level's own render tables
    assert vevm.size_report()["cache_bytes"] >= (level.size_report()["total_bytes"]
                                                 + level.size_report()["cache_bytes"])
    vevm.cache.clear()
    assert vevm.cache.keys() == []
    again, _ = render(vevm, camera(vevm, g, "x"), BONE, method="raycast", level=2)
    np.testing.assert_array_equal(again, rgba)


def test_the_default_budget_scales_with_the_grid():
    small = VolumeEVM.from_volume(phantoms.box((16, 16, 16), lo=(4, 4, 4), hi=(12, 12, 12)), 0.5)
    assert small.cache.budget == 256 << 20
    assert DerivedCache(budget=5).budget == 5
    big = VolumeEVM(small.evm, small.table(), shape=(600, 600, 600))
    assert big.cache.budget == 96 * 602 ** 3


def test_least_recently_used_entries_go_first():
    cache = DerivedCache(budget=3 * 800)
    for name in "abc":
        cache.get(name, lambda: np.ones(100))
    cache.get("a", None)  # kept: make is not called; "a" becomes the most recent
    cache.get("d", lambda: np.ones(100))
    assert cache.keys() == ["c", "a", "d"] and "b" not in cache
    assert cache.nbytes == 2400
    cache.budget = 1000
    assert cache.keys() == ["d"]
    cache.discard("d")
    cache.discard("d")
    assert len(cache) == 0
    huge = cache.get("huge", lambda: np.ones(1000))  # larger than the budget: not kept
    assert np.array_equal(huge, np.ones(1000)) and "huge" not in cache


def test_held_bytes_counts_each_array_once():
    shared = np.zeros(10)

    class Holder:
        def __init__(self):
            self.arrays = [shared, np.zeros(5, np.int32)]
            self.name = "holder"
            self.how = len

    assert held_bytes((shared, {"a": shared, "b": np.zeros(2)})) == 80 + 16
    assert held_bytes(Holder()) == 80 + 20

    class Slotted:
        __slots__ = ("array", "empty")

        def __init__(self):
            self.array = np.zeros(4)

    assert held_bytes(Slotted()) == 32
    nested = DerivedCache(budget=1000)
    nested.get("x", lambda: np.zeros(3))
    assert held_bytes([nested, 7, "text", np]) == 24


@pytest.mark.parametrize("bad", [-1, 1.5, "512M", None, True])
def test_bad_budgets_raise(bad):
    with pytest.raises(VolumeEVMError, match="budget"):
        DerivedCache(budget=bad)
    cache = DerivedCache(budget=10)
    with pytest.raises(VolumeEVMError, match="budget"):
        cache.budget = bad
    assert cache.budget == 10


def test_threads_asking_for_one_missing_entry_make_it_once():
    """A render job's thread and the viewport's may ask for the same table at once: one makes
    it, the other waits for it and gets the same entry; another key is made meanwhile."""

    cache = DerivedCache(budget=1 << 20)
    calls, started = [], threading.Event()

    def slow():
        calls.append("table")
        started.set()
        time.sleep(0.2)
        return np.ones(10)

    got = {}
    first = threading.Thread(target=lambda: got.setdefault("a", cache.get("table", slow)))
    first.start()
    started.wait()
    other = cache.get("other", lambda: np.zeros(3))  # not held up by the slow table
    assert "table" not in cache and np.array_equal(other, np.zeros(3))
    got["b"] = cache.get("table", slow)  # waits for the first thread's table
    first.join()
    assert calls == ["table"] and got["a"] is got["b"]
