"""Label maps: one sweep builds every label exactly as its own band build, and the exact
measurements of regions and label sets (volume, area, shared faces, box, centroid, parts)."""

import csv
import dataclasses
import itertools
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volumeevm_addon import (
    EVM,
    LabelSet,
    Volume,
    VolumeEVM,
    VolumeEVMError,
    phantoms,
    set_kernel_threads,
)
from volumeevm_addon.model import LabelInfo, box_evm


@pytest.fixture(scope="module")
def liver(data_dir):
    """The real liver label map (labels 84, 85, 127, 255) and its spacing."""
    meta = json.loads((data_dir / "seg_liver_cgal.json").read_text())
    return np.load(data_dir / "seg_liver_cgal.npy"), tuple(meta["spacing_mm"])


def assert_same_as_band_builds(regions, array, **geometry):
    """Each region equals ``from_array(array, L, upper=L)``: vertices, table, every field."""
    present = sorted(int(v) for v in np.unique(array) if v != 0)
    assert sorted(regions) == present
    for label, region in regions.items():
        band = VolumeEVM.from_array(array, label, upper=label, **geometry)
        assert region.evm == band.evm, label
        assert region.table(0).dtype == band.table(0).dtype
        assert np.array_equal(region.table(0), band.table(0))
        for field in ("shape", "spacing", "origin", "units", "threshold", "upper"):
            assert getattr(region, field) == getattr(band, field), field
        assert np.array_equal(region.orientation, band.orientation)


def test_the_liver_map_builds_every_label_as_its_band_build(liver):
    array, spacing = liver
    regions = VolumeEVM.from_labels(array, spacing=spacing)
    assert_same_as_band_builds(regions, array, spacing=spacing)
    # The labels are a partition of the foreground: their EVMs XOR to the foreground's.
    foreground = EVM()
    for region in regions.values():
        foreground = foreground ^ region.evm
    assert foreground == EVM.from_mask(array > 0)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 5, 1), (6, 1, 7), (9, 8, 7), (40, 3, 5)])
def test_random_maps_build_every_label_as_its_band_build(seed, shape):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 2 + seed, shape)  # from 2 labels with background to 7
    dtype = [np.uint8, np.int16, np.uint16, np.int32, np.int64, np.uint32][seed]
    array = labels.astype(dtype)
    assert_same_as_band_builds(VolumeEVM.from_labels(array), array)


@st.composite
def painted_label_maps(draw):
    """Small label maps painted box by box: many labels (up to 300), touching one another
    across faces, edges and corners, reaching the grid's borders, and some labels of single
    voxels; in a dtype drawn from the integer types."""
    shape = draw(st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)))
    dtype = draw(st.sampled_from([np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.int64]))
    top = min(np.iinfo(dtype).max, 300)
    array = np.full(shape, draw(st.integers(0, 3)), dtype)  # background or a first label
    for _ in range(draw(st.integers(0, 40))):
        lo = [draw(st.integers(0, n - 1)) for n in shape]
        hi = [draw(st.integers(low + 1, n)) for low, n in zip(lo, shape)]
        array[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = draw(st.integers(0, top))
    if draw(st.booleans()):  # speckle: points where three or more labels meet everywhere
        noise = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        speckle = noise.random(shape) < draw(st.sampled_from([0.05, 0.3, 1.0]))
        array[speckle] = noise.integers(0, top + 1, int(speckle.sum()))
    return array


@settings(max_examples=150, deadline=None)
@given(painted_label_maps())
def test_painted_label_maps_build_every_label_as_its_band_build(array):
    assert_same_as_band_builds(VolumeEVM.from_labels(array), array)


@pytest.mark.parametrize("scale", [1, 70_000, 10**9], ids=["narrow", "wide", "sparse"])
def test_label_values_far_apart_are_built_all_the_same(scale):
    """Values up to 65536 number themselves, larger ones up to 2**22 only the values present, and
    larger ones still are renumbered by sorting (0 kept as the background around the grid,
    with or without 0 in the map): the same regions in every case."""
    array = np.random.default_rng(3).integers(0, 4, (7, 9, 8)).astype(np.int64) * scale
    assert_same_as_band_builds(VolumeEVM.from_labels(array), array)
    array += scale  # no background at all
    assert_same_as_band_builds(VolumeEVM.from_labels(array), array)


def test_the_result_does_not_depend_on_the_thread_count(liver):
    array, _ = liver
    try:
        set_kernel_threads(1)
        one = VolumeEVM.from_labels(array)
        set_kernel_threads(2)
        two = VolumeEVM.from_labels(array)
    finally:
        set_kernel_threads(None)
    assert list(one) == list(two)
    assert all(one[label].evm == two[label].evm for label in one)


def test_a_volume_brings_its_geometry_units_and_name():
    box = phantoms.box((8, 9, 10), lo=(1, 2, 3), hi=(5, 6, 7), density=4, spacing=(0.5, 1.0, 2.0))
    vol = dataclasses.replace(box, array=box.array.astype(np.uint8))
    (label, region), = VolumeEVM.from_labels(vol).items()
    assert label == 4 and region.voxel_count == 64
    assert region.spacing == (0.5, 1.0, 2.0) and region.units == vol.units
    with pytest.raises(VolumeEVMError, match="spacing: a Volume brings its own geometry"):
        VolumeEVM.from_labels(vol, spacing=(1, 1, 1))


def test_chosen_labels_and_an_empty_one_reported_not_fatal():
    array = np.zeros((6, 6, 6), np.uint8)
    array[:2], array[2:4], array[4:] = 1, 2, 3
    regions = VolumeEVM.from_labels(array, labels=(label for label in (3, 1)))
    assert list(regions) == [1, 3]
    assert list(VolumeEVM.from_labels(array, labels=np.uint8(2))) == [2]
    assert regions[3] .evm == VolumeEVM.from_array(array, 3, upper=3).evm
    with pytest.warns(UserWarning, match=r"array: labels \[9\] have no voxels"):
        regions = VolumeEVM.from_labels(array, labels=[2, 9])
    assert list(regions) == [2]


@pytest.mark.parametrize("array, message", [
    (np.ones((3, 3, 3)), "must hold integers, got dtype float64 .*astype"),
    (np.ones((3, 3, 3), bool), "boolean mask is one region: use EVM.from_mask"),
    (np.full((3, 3, 3), -1, np.int16), "27 voxels are negative"),
    (np.ones((3, 3), np.uint8), "non-empty 3-D array, got shape \\(3, 3\\)"),
    (np.zeros((0, 3, 3), np.uint8), "non-empty 3-D array"),
])
def test_what_is_not_a_label_map_is_refused_by_name(array, message):
    with pytest.raises(VolumeEVMError, match="^array: .*" + message):
        VolumeEVM.from_labels(array)


@pytest.mark.parametrize("labels", [[0, 1], [-2], [], ["liver"], [1.5], "12", [[1, 2]], 0])
def test_bad_label_choices_are_refused(labels):
    with pytest.raises(VolumeEVMError, match="labels must be"):
        VolumeEVM.from_labels(np.ones((2, 2, 2), np.uint8), labels=labels)


def test_more_than_65536_labels_are_refused_unless_some_are_picked():
    array = np.arange(1, 2 * 3 * 10923 + 1, dtype=np.int32).reshape(2, 3, 10923)  # 65538 labels
    with pytest.raises(VolumeEVMError, match="65538 labels, more than the 65536 .*labels="):
        VolumeEVM.from_labels(array)
    regions = VolumeEVM.from_labels(array, labels=[5, 40000])
    assert {label: r.voxel_count for label, r in regions.items()} == {5: 1, 40000: 1}
    assert regions[40000].evm == VolumeEVM.from_array(array, 40000, upper=40000).evm


# ---------------------------------------------------------------------- measurements
def test_a_box_measures_its_closed_forms():
    spacing = (0.5, 1.25, 2.0)
    array = np.zeros((10, 10, 10), np.int16)
    array[1:5, 2:8, 3:4] = 7  # 4 x 6 x 1 voxels
    m = VolumeEVM.from_array(array, 7, spacing=spacing, origin=(10.0, 20.0, 30.0)).measure()
    sx, sy, sz = spacing
    assert m["voxels"] == 24
    assert m["volume_mm3"] == 24 * sx * sy * sz and m["volume_ml"] == m["volume_mm3"] / 1000
    assert m["area_mm2"] == pytest.approx(2 * (6 * 1 * sy * sz + 4 * 1 * sx * sz + 4 * 6 * sx * sy),
                                          rel=1e-15)
    # Voxel centre (i, j, k) sits at origin + index * spacing; corners half a voxel out.
    assert m["bbox_mm"] == ((10.0 + 0.5 * sx, 20.0 + 1.5 * sy, 30.0 + 2.5 * sz),
                            (10.0 + 4.5 * sx, 20.0 + 7.5 * sy, 30.0 + 3.5 * sz))
    assert m["centroid_mm"] == (10.0 + 2.5 * sx, 20.0 + 4.5 * sy, 30.0 + 3.0 * sz)
    assert m["components"] == 1


def test_a_ball_measures_its_voxel_count_and_a_turned_grid_turns_the_centroid():
    centre = np.array([12.0, 9.0, 10.0])
    grid = np.stack(np.meshgrid(*map(np.arange, (25, 19, 21)), indexing="ij"), axis=-1)
    array = (np.linalg.norm(grid - centre, axis=-1) <= 7.3).astype(np.uint8)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    vevm = VolumeEVM.from_array(array, 1, spacing=(0.7, 0.7, 1.1), origin=(5.0, 0.0, -3.0),
                                orientation=turn)
    m = vevm.measure()
    count = int(array.sum())
    assert m["voxels"] == count and m["volume_mm3"] == pytest.approx(count * 0.7 * 0.7 * 1.1,
                                                                      rel=1e-15)
    # A ball's voxels are symmetric about its centre voxel: the centroid is that voxel's centre.
    expected = vevm.index_to_physical() @ np.append(centre, 1.0)
    assert m["centroid_mm"] == pytest.approx(tuple(expected[:3]), abs=1e-12)
    # Area: every inside voxel's faces against outside voxels, counted directly.
    padded = np.pad(array, 1)
    faces = [np.count_nonzero(np.diff(padded, axis=axis)) for axis in range(3)]
    sx, sy, sz = 0.7, 0.7, 1.1
    assert m["area_mm2"] == pytest.approx(faces[0] * sy * sz + faces[1] * sx * sz
                                          + faces[2] * sx * sy, rel=1e-14)
    assert m["components"] == 1


@pytest.mark.parametrize("radius, spacing", [(40, (1.0, 1.0, 1.0)), (80, (0.5, 0.5, 0.5))])
def test_a_voxel_sphere_has_one_and_a_half_times_the_smooth_area(radius, spacing):
    # The faces' area is the smooth area times |n_x| + |n_y| + |n_z|, whose mean over a sphere
    # is 3 * 1/2: what the sidebar's note says. The volume matches the smooth sphere's.
    n = 2 * radius + 2
    grid = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1)
    array = (np.linalg.norm(grid - (n - 1) / 2, axis=-1) <= radius).astype(np.uint8)
    m = VolumeEVM.from_array(array, 1, spacing=spacing).measure()
    r_mm = radius * spacing[0]
    assert m["area_mm2"] / (4 * math.pi * r_mm ** 2) == pytest.approx(1.5, abs=1e-3)
    assert m["volume_mm3"] / (4 / 3 * math.pi * r_mm ** 3) == pytest.approx(1.0, abs=1e-3)


def test_parts_and_an_emptied_region():
    array = np.zeros((9, 9, 9), np.uint8)
    array[0:2, 0:2, 0:2] = array[5:9, 5:9, 5:9] = array[0, 8, 8] = 1
    vevm = VolumeEVM.from_array(array, 1)
    assert vevm.measure()["components"] == 3
    empty = VolumeEVM(EVM(), np.zeros(0), shape=(9, 9, 9)).measure()
    assert empty == {"voxels": 0, "volume_mm3": 0.0, "volume_ml": 0.0, "area_mm2": 0.0,
                     "bbox_mm": None, "centroid_mm": None, "components": 0}


def test_shared_areas_of_the_liver_labels_equal_the_touching_voxel_faces(liver):
    array, spacing = liver
    measured = VolumeEVM.from_labels(array, spacing=spacing).measure()
    # Brute force: every pair of face-adjacent voxels with two different non-zero labels.
    face_mm2 = (spacing[1] * spacing[2], spacing[0] * spacing[2], spacing[0] * spacing[1])
    expected = {}
    for axis in range(3):
        a = np.moveaxis(array, axis, 0)
        lo, hi = a[:-1].ravel(), a[1:].ravel()
        touching = (lo != hi) & (lo > 0) & (hi > 0)
        pairs, counts = np.unique(np.sort(np.stack([lo[touching], hi[touching]]), axis=0),
                                  axis=1, return_counts=True)
        for (p, q), n in zip(pairs.T.tolist(), counts.tolist()):
            expected[p, q] = expected.get((p, q), 0.0) + n * face_mm2[axis]
    assert expected  # the liver's labels do touch
    got = {(p, q): area for p, row in measured.items() for q, area in row["shared_area_mm2"].items()
           if p < q}
    assert got.keys() == expected.keys()
    for pair, area in expected.items():
        assert got[pair] == pytest.approx(area, rel=1e-12)
        assert (measured[pair[0]]["shared_area_mm2"][pair[1]]
                == measured[pair[1]]["shared_area_mm2"][pair[0]])
    # Each label's own volume is its voxel count.
    for label, row in measured.items():
        assert row["voxels"] == int(np.count_nonzero(array == label))
        assert row["volume_ml"] == pytest.approx(row["voxels"] * math.prod(spacing) / 1000,
                                                 rel=1e-15)


def test_measurements_as_csv(tmp_path):
    array = np.zeros((6, 6, 6), np.uint8)
    array[:3], array[3:, :2] = 1, 2
    infos = {1: LabelInfo("part 1", (1.0, 0.0, 0.0)), 2: LabelInfo("part, 2", (0.0, 0.0, 1.0))}
    volume = Volume(array, spacing=(1.0, 2.0, 0.5), labels=infos)
    regions = VolumeEVM.from_labels(volume)
    assert regions.infos == infos
    measured = regions.measure()
    rows = [{"label": label, **row} for label, row in measured.items()]
    path = regions.write_measurements(tmp_path / "labels.csv")
    with open(path, newline="") as file:
        read = list(csv.DictReader(file))
    assert [r["name"] for r in read] == ["part 1", "part, 2"]
    for row, back in zip(rows, read):
        assert int(back["voxels"]) == row["voxels"]
        assert float(back["volume_mm3"]) == pytest.approx(row["volume_mm3"], rel=1e-6)
        assert float(back["area_mm2"]) == pytest.approx(row["area_mm2"], rel=1e-6)
        assert tuple(map(float, back["centroid_mm"].split())) == pytest.approx(row["centroid_mm"],
                                                                               rel=1e-6)
    with pytest.raises(VolumeEVMError, match="labels.csv"):
        regions.write_measurements(path)
    with open(path, newline="") as file:
        assert list(csv.DictReader(file))[0]["name"] == "part 1"  # left as it was


def test_labels_touching_across_every_axis_share_exactly_their_contact():
    """Two labels in a 3-D checkerboard touch on every face: each voxel's 6 faces are shared
    (inside the grid), so the shared area is the whole boundary minus the grid's outside."""
    index = np.indices((4, 4, 4)).sum(axis=0)
    array = (1 + index % 2).astype(np.uint8)
    measured = VolumeEVM.from_labels(array).measure()
    inner_faces = 3 * 3 * 4 * 4  # per axis: 3 planes inside of 4 x 4 faces
    assert measured[1]["shared_area_mm2"] == {2: float(inner_faces)}
    assert measured[1]["area_mm2"] + measured[2]["area_mm2"] == 2 * inner_faces + 6 * 16
    assert all(itertools.chain(row["components"] == 32 for row in measured.values()))


# ---------------------------------------------------------------------- edits of all labels
def _dense_labels(regions, shape):
    """The label map a set stands for, rebuilt voxel by voxel (and each region's densities are
    its label)."""
    out = np.zeros(shape, np.int64)
    for label, region in regions.items():
        assert np.all(region.table(0) == label)
        mask = region.evm.to_mask(shape)
        assert not (out[mask] != 0).any()  # disjoint
        out[mask] = label
    return out


def test_cut_keep_and_add_act_on_every_label_as_on_the_map(liver):
    array, spacing = liver
    crop = array[150:260, 120:230, 40:120]  # three labels meet here
    regions = VolumeEVM.from_labels(crop, spacing=spacing)
    assert len(regions) == 3
    tool_mask = np.zeros(crop.shape, bool)
    tool_mask[30:90, 20:70, 10:60] = True
    tool = EVM.from_mask(tool_mask)
    for edited, expected in [(regions.cut(tool), np.where(tool_mask, 0, crop)),
                             (regions.keep(tool), np.where(tool_mask, crop, 0)),
                             (regions.add(tool, 85), np.where(tool_mask, 85, crop)),
                             (regions.add(tool, 7), np.where(tool_mask, 7, crop))]:
        assert isinstance(edited, LabelSet)
        assert np.array_equal(_dense_labels(edited, crop.shape), expected)
        for label, region in edited.items():  # as a build from the edited map
            assert region.evm == VolumeEVM.from_array(expected, label, upper=label).evm
            assert region.threshold == region.upper == label
    assert regions.add(tool, 7).infos[7] == LabelInfo("label 7",
                                                      regions.add(tool, 7).infos[7].color)


def test_a_label_an_edit_empties_leaves_the_set():
    array = np.zeros((6, 6, 6), np.uint8)
    array[:2], array[4:] = 1, 2
    regions = VolumeEVM.from_labels(array)
    assert list(regions.cut(box_evm((0, 0, 0), (2, 6, 6), (6, 6, 6)))) == [2]
    assert list(regions.keep(box_evm((0, 0, 0), (3, 6, 6), (6, 6, 6)))) == [1]
    assert list(regions.add(box_evm((0, 0, 0), (6, 6, 6), (6, 6, 6)), 2)) == [2]
    with pytest.raises(VolumeEVMError, match="cut: the result would be empty"):
        regions.cut(box_evm((0, 0, 0), (6, 6, 6), (6, 6, 6)))
    with pytest.raises(VolumeEVMError, match="keep inside: the result would be empty"):
        regions.keep(box_evm((2, 0, 0), (4, 6, 6), (6, 6, 6)))
    with pytest.raises(VolumeEVMError, match="add: the tool has no voxel inside"):
        regions.add(EVM.from_mask(np.ones((2, 2, 2), bool), offset=(7, 7, 7)), 1)
    with pytest.raises(VolumeEVMError, match="add: label must be an integer > 0, got 0"):
        regions.add(box_evm((0, 0, 0), (1, 1, 1), (6, 6, 6)), 0)


def test_regions_of_different_grids_are_not_a_set():
    a = VolumeEVM.from_array(np.ones((2, 2, 2)), 1)
    b = VolumeEVM.from_array(np.ones((2, 2, 3)), 1)
    with pytest.raises(VolumeEVMError, match="share one grid"):
        LabelSet({1: a, 2: b})


def _unit_faces(evm):
    """Every unit face of an EVM's mesh as rows ``(axis, plane, b, c, sign)``: each polygon is
    a rectangle (with collinear T-junction corners) in a lattice plane, cut into its unit
    squares; ``sign`` is the side its outward normal points to."""
    vertices, polygons = evm.mesh()
    rows = []
    for loop in polygons:
        corners = vertices[loop].astype(np.int64)
        axis = int(np.flatnonzero(np.ptp(corners, axis=0) == 0)[0])
        b_axis, c_axis = [a for a in range(3) if a != axis]
        e1, e2 = corners[1] - corners[0], corners[2] - corners[1]
        normal = (np.cross(e1, e2) if np.cross(e1, e2).any()
                  else np.cross(corners[2] - corners[0], corners[-1] - corners[0]))
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        b, c = np.meshgrid(np.arange(lo[b_axis], hi[b_axis]), np.arange(lo[c_axis], hi[c_axis]),
                           indexing="ij")
        rows.append(np.stack([np.full(b.size, axis), np.full(b.size, lo[axis]), b.ravel(),
                              c.ravel(), np.full(b.size, np.sign(normal[axis]))], axis=1))
    return np.concatenate(rows)


def test_touching_labels_meshes_cover_their_contact_exactly_once_from_each_side(liver):
    """No gap, no overlap: the unit faces of a label's mesh that face another label's are
    exactly the voxel faces the two labels share, each covered once by each mesh, with
    opposite normals."""
    array, _ = liver
    crop = array[150:260, 120:230, 40:120]
    regions = VolumeEVM.from_labels(crop)
    faces = {label: _unit_faces(region.evm) for label, region in regions.items()}
    for label, rows in faces.items():  # each mesh covers each unit face once: no overlap
        assert len(np.unique(rows[:, :4], axis=0)) == len(rows)
        assert len(rows) == regions[label].evm.area()
    shared = 0
    for p, q in itertools.combinations(regions, 2):
        fp, fq = faces[p], faces[q]
        common = {tuple(r[:4]) for r in fp} & {tuple(r[:4]) for r in fq}
        # Brute force: voxel faces between p and q, as (axis, plane, b, c).
        expected = set()
        for axis in range(3):
            a = np.moveaxis(crop, axis, 0)
            touching = ((a[:-1] == p) & (a[1:] == q)) | ((a[:-1] == q) & (a[1:] == p))
            for plane, b, c in zip(*np.nonzero(touching)):
                expected.add((axis, plane + 1, b, c))
        assert common == expected, (p, q)
        sign_p = {tuple(r[:4]): r[4] for r in fp}
        sign_q = {tuple(r[:4]): r[4] for r in fq}
        assert all(sign_p[f] == -sign_q[f] for f in common)
        shared += len(common)
    assert shared > 1000  # the labels do touch, over many faces


def _lattice(vertices):
    """Mesh vertices of the default geometry (1 mm voxels at the origin) back on the lattice."""
    lattice = vertices + 0.5
    assert np.array_equal(lattice, np.round(lattice))
    return lattice.astype(np.int64)


def _cycles(mesh):
    """Each polygon of a mesh (default geometry) as its corner cycle (lattice points), from its
    smallest corner: the same polygon with the opposite orientation is the reversed cycle."""
    vertices, polygons = mesh
    points = [tuple(p) for p in _lattice(vertices).tolist()]
    cycles = []
    for loop in polygons:
        corners = [points[i] for i in loop]
        first = corners.index(min(corners))
        cycles.append(tuple(corners[first:] + corners[:first]))
    return cycles


def _reversed(cycle):
    return (cycle[0],) + tuple(reversed(cycle[1:]))


def _assert_closed(mesh):
    """Every directed edge of the mesh matched by the opposite one (an edge where voxels touch
    only along it has two each way)."""
    vertices, polygons = mesh
    u, v = polygons.edges()
    assert not (u == v).any()
    n = len(vertices)
    assert np.array_equal(np.sort(u.astype(np.int64) * n + v), np.sort(v.astype(np.int64) * n + u))


def _rectangles(mesh):
    """Each polygon's axis, plane, and extent ``[lo, hi)`` along the two other axes (in
    increasing axis order), as rows ``(axis, plane, lo b, hi b, lo c, hi c)``."""
    vertices, polygons = mesh
    corners = _lattice(vertices)[polygons.indices]
    lo = np.minimum.reduceat(corners, polygons.starts)
    hi = np.maximum.reduceat(corners, polygons.starts)
    axis = np.argmax(lo == hi, axis=1)
    assert ((lo == hi).sum(axis=1) == 1).all()
    others = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    rows = np.arange(len(axis))
    return np.stack([axis, lo[rows, axis], lo[rows, others[:, 0]], hi[rows, others[:, 0]],
                     lo[rows, others[:, 1]], hi[rows, others[:, 1]]], axis=1)


def _face_codes(shape, axis, plane, b, c):
    """Unit faces ``(axis, plane, b, c)`` of a grid of ``shape`` voxels as distinct integers
    (``b`` and ``c`` along the other two axes, in increasing axis order)."""
    n = max(shape) + 1
    return ((np.asarray(axis, np.int64) * n + plane) * n + b) * n + c


def _contacts(array):
    """The voxel faces between every two touching labels, as :func:`_face_codes`:
    ``{(p, q): codes}`` with ``p < q``."""
    found = {}
    for axis in range(3):
        a = np.moveaxis(array, axis, 0)
        plane, b, c = np.nonzero((a[:-1] != a[1:]) & (a[:-1] > 0) & (a[1:] > 0))
        lo, hi = a[:-1][plane, b, c], a[1:][plane, b, c]
        codes = _face_codes(array.shape, axis, plane + 1, b, c)
        for pair in set(zip(np.minimum(lo, hi).tolist(), np.maximum(lo, hi).tolist())):
            at = (np.minimum(lo, hi) == pair[0]) & (np.maximum(lo, hi) == pair[1])
            found[pair] = np.concatenate([found.get(pair, np.zeros(0, np.int64)), codes[at]])
    return found


def assert_touching_labels_carry_the_same_polygons(array, meshes):
    """For every ordered pair of labels ``p, q``: each polygon of ``p``'s mesh that covers a
    voxel face between them lies wholly within their contact and is, reversed, a polygon of
    ``q``'s mesh; each mesh is closed and covers its label's boundary once. Returns the number
    of contact polygons seen."""
    cycles = {label: _cycles(mesh) for label, mesh in meshes.items()}
    faces = {}
    for label, mesh in meshes.items():
        _assert_closed(mesh)
        axis, plane, b0, b1, c0, c1 = _rectangles(mesh).T
        area = (b1 - b0) * (c1 - c0)
        polygon = np.repeat(np.arange(len(area)), area)  # each unit face's polygon
        k = np.arange(len(polygon)) - np.repeat(np.cumsum(area) - area, area)
        width = (c1 - c0)[polygon]
        codes = _face_codes(array.shape, axis[polygon], plane[polygon], b0[polygon] + k // width,
                            c0[polygon] + k % width)
        assert len(np.unique(codes)) == len(codes) == EVM.from_mask(array == label).area()
        faces[label] = codes, polygon, area
    contacts = _contacts(array)
    seen = 0
    for p, q in itertools.permutations(meshes, 2):
        codes, polygon, area = faces[p]
        contact = contacts.get((min(p, q), max(p, q)), np.zeros(0, np.int64))
        count = np.bincount(polygon[np.isin(codes, contact)], minlength=len(area))
        touching = np.flatnonzero(count)
        assert np.array_equal(count[touching], area[touching]), (p, q)  # within the contact
        theirs = set(cycles[q])
        assert all(_reversed(cycles[p][k]) in theirs for k in touching), (p, q)
        seen += len(touching)
    return seen


def test_touching_labels_meshes_carry_the_same_polygons_reversed(liver):
    """The label meshes (LabelSet.meshes, what Make Label Meshes shows) of the liver crop where
    three labels meet and of the whole map: every polygon at a contact lies within it and is
    the neighbour's polygon reversed, vertex for vertex."""
    array, _ = liver
    for part in (array[150:260, 120:230, 40:120], array):
        regions = VolumeEVM.from_labels(part)
        meshes = regions.meshes()
        assert list(meshes) == list(regions)
        assert assert_touching_labels_carry_the_same_polygons(part, meshes) > 1000


def _face_cycles(rectangles, points):
    """The cycles of axis-aligned rectangles given as ``(axis, plane, (lo, hi) along the next
    axis, (lo, hi) along the one after, sign of the normal)``, counter-clockwise seen from
    outside, with every one of ``points`` that lies strictly inside a side inserted (the
    T-junction rule), each from its smallest corner."""
    cycles = set()
    for axis, plane, (b0, b1), (c0, c1), sign in rectangles:
        def point(b, c):
            p = [0, 0, 0]
            p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3] = plane, b, c
            return tuple(p)

        corners = [point(b0, c0), point(b1, c0), point(b1, c1), point(b0, c1)]
        if sign < 0:
            corners.reverse()
        loop = []
        for start, end in zip(corners, corners[1:] + corners[:1]):
            loop.append(start)
            step = np.sign(np.subtract(end, start))
            inside = [x for x in points if np.array_equal(np.sign(np.subtract(x, start)), step)
                      and np.array_equal(np.sign(np.subtract(end, x)), step)
                      and np.count_nonzero(np.subtract(x, start)) == 1]
            loop += sorted(inside, key=lambda x: np.abs(np.subtract(x, start)).sum())
        first = loop.index(min(loop))
        cycles.add(tuple(loop[first:] + loop[:first]))
    return cycles


def _box_rectangles(lo, hi):
    """The six faces of the box ``[lo, hi)`` for :func:`_face_cycles`."""
    faces = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        faces += [(axis, hi[axis], (lo[b], hi[b]), (lo[c], hi[c]), 1),
                  (axis, lo[axis], (lo[b], hi[b]), (lo[c], hi[c]), -1)]
    return faces


def _all_corners(rectangles):
    return {corner for cycle in _face_cycles(rectangles, ()) for corner in cycle}


def test_two_boxes_of_different_sizes_share_one_polygon():
    """A 4-voxel cube with a 2 x 2 x 1 box on its side x = 4: that side is the contact square
    and the four rectangles of the background around it (cut along y first, then z), whose
    corners on the neighbouring faces' edges are inserted there."""
    array = np.zeros((7, 6, 6), np.uint8)
    array[0:4, 0:4, 0:4] = 1
    array[4:6, 1:3, 1:2] = 2
    meshes = VolumeEVM.from_labels(array).meshes()
    cube = [f for f in _box_rectangles((0, 0, 0), (4, 4, 4)) if f[:2] != (0, 4)]
    side = [(0, 4, (0, 1), (0, 4), 1), (0, 4, (1, 3), (0, 1), 1), (0, 4, (1, 3), (2, 4), 1),
            (0, 4, (3, 4), (0, 4), 1), (0, 4, (1, 3), (1, 2), 1)]
    small = _box_rectangles((4, 1, 1), (6, 3, 2))
    corners = _all_corners(cube + side + small)
    assert set(_cycles(meshes[1])) == _face_cycles(cube + side, corners)
    assert set(_cycles(meshes[2])) == _face_cycles(small, corners)
    assert len(meshes[1][1]) == 10 and len(meshes[2][1]) == 6
    contact = _face_cycles([side[-1]], corners).pop()
    assert contact == ((4, 1, 1), (4, 3, 1), (4, 3, 2), (4, 1, 2))
    assert _reversed(contact) in _cycles(meshes[2])
    assert assert_touching_labels_carry_the_same_polygons(array, meshes) == 2
    # A label's own mesh merges the cube's side into one square, across the contact.
    assert len(VolumeEVM.from_labels(array)[1].mesh()[1]) == 6


def test_a_slab_under_a_checkerboard_of_two_labels():
    """Label 1 fills x < 2 of a 6 x 6 cross-section; above it, blocks of 2 x 2 x 2 voxels
    alternate between labels 2 and 3. The slab's top is cut into the nine blocks' squares (no
    merging across a change of neighbour), its four sides take the blocks' corners on their top
    edges, and every block is its six squares."""
    array = np.ones((4, 6, 6), np.uint8)
    blocks = {2: [], 3: []}
    for yb, zb in itertools.product(range(3), range(3)):
        label = 2 + (yb + zb) % 2
        array[2:4, 2 * yb:2 * yb + 2, 2 * zb:2 * zb + 2] = label
        blocks[label].append(((2, 2 * yb, 2 * zb), (4, 2 * yb + 2, 2 * zb + 2)))
    meshes = VolumeEVM.from_labels(array).meshes()
    slab = [f for f in _box_rectangles((0, 0, 0), (2, 6, 6)) if f[:2] != (0, 2)]
    slab += [(0, 2, (y, y + 2), (z, z + 2), 1) for y, z in itertools.product((0, 2, 4), repeat=2)]
    expected = {1: slab, 2: [], 3: []}
    for label, boxes in blocks.items():
        for lo, hi in boxes:
            expected[label] += _box_rectangles(lo, hi)
    corners = _all_corners([f for faces in expected.values() for f in faces])
    for label, faces in expected.items():
        assert sorted(_cycles(meshes[label])) == sorted(_face_cycles(faces, corners)), label
    assert [len(meshes[label][1]) for label in (1, 2, 3)] == [14, 30, 24]
    sides = [c for c in _cycles(meshes[1]) if len(c) == 6]
    assert len(sides) == 4  # each side: 4 corners and the 2 block corners on its top edge
    assert assert_touching_labels_carry_the_same_polygons(array, meshes) == 2 * (9 + 12)


def test_one_label_alone_gets_its_own_mesh_exactly():
    """With nothing to agree with, a label's mesh is EVM.mesh's, array for array."""
    mask = np.random.default_rng(4).random((12, 11, 10)) < 0.5
    (label, (vertices, polygons)), = VolumeEVM.from_labels(mask.astype(np.uint8)).meshes().items()
    lattice, own = EVM.from_mask(mask).mesh()
    assert np.array_equal(vertices, lattice - 0.5)
    for field in ("indices", "starts", "sizes"):
        assert np.array_equal(getattr(polygons, field), getattr(own, field))


@pytest.mark.parametrize("seed", range(4))
def test_random_label_maps_carry_the_same_polygons(seed):
    array = np.random.default_rng(seed).integers(0, 3 + seed, (9, 8, 7))  # 2 to 5 labels
    meshes = VolumeEVM.from_labels(array).meshes()
    assert assert_touching_labels_carry_the_same_polygons(array, meshes) > 0


def test_manifold_and_smooth_label_meshes(liver):
    """The label meshes made 2-manifold (for 3D printing) and smooth (for display), label by
    label: each is the core's split, or relaxation, of that label's mesh."""
    from test_manifold import assert_near_lattice, assert_two_manifold
    from test_smooth_mesh import walk_faces

    array, _ = liver
    regions = VolumeEVM.from_labels(array[150:260, 120:230, 40:120])
    exact = {label: (vertices + 0.5, polygons)
             for label, (vertices, polygons) in regions.meshes().items()}
    for label, (vertices, polygons) in regions.meshes(manifold=True).items():
        assert_two_manifold(vertices, polygons)
        assert_near_lattice((vertices + 0.5, polygons), exact[label])
    for label, (vertices, polygons) in regions.meshes(smooth=True).items():
        moved = vertices + 0.5
        centres = walk_faces(exact[label], (moved, polygons))
        offset = np.abs(moved - np.concatenate([exact[label][0], centres]))
        assert 0.1 < offset.max() <= 0.5 + 1e-12


def test_overlapping_segments_each_get_a_closed_mesh_of_their_own_faces(data_dir):
    """The Slicer segmentation in two layers, whose segments overlap: each segment's mesh is
    closed and covers its own boundary once, whatever lies across it."""
    from volumeevm_addon import read_volume

    path = data_dir / "slicer" / "SegmentationOverlapping.seg.nrrd"
    regions = VolumeEVM.from_labels(read_volume(path))
    masks = {label: region.evm.to_mask(region.shape) for label, region in regions.items()}
    assert any((masks[p] & masks[q]).any() for p, q in itertools.combinations(masks, 2))
    for label, (vertices, polygons) in regions.meshes().items():
        matrix = regions[label].index_to_physical()
        lattice = np.linalg.solve(matrix[:3, :3], (vertices - matrix[:3, 3]).T).T + 0.5
        assert np.abs(lattice - np.round(lattice)).max() < 1e-6
        mesh = np.round(lattice) - 0.5, polygons  # as in the default geometry
        _assert_closed(mesh)
        r = _rectangles(mesh)
        assert ((r[:, 3] - r[:, 2]) * (r[:, 5] - r[:, 4])).sum() == regions[label].evm.area()
