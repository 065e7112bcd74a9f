"""Exact measurements of voxel regions: volume, boundary area, bounding box, centroid, parts.

Every number here is an exact property of the voxel model, not an estimate: the volume is the
voxel count times the voxel's volume, the area is the sum of the boundary's voxel faces (each
axis's faces times their physical size), the centroid is the mean of the voxel centres. A
smooth surface through the same voxels is smaller in area: faces that step along an oblique
surface count each step, so the staircase's area is the smooth area times
``|n_x| + |n_y| + |n_z|`` (n the smooth normal), from 1 (a face parallel to the grid) to
``sqrt(3)`` (a diagonal), 1.5 on average over all directions (a sphere). Volumes agree with a
smooth surface through the voxels' boundary to within half a voxel layer of the surface.

Shared areas between labels come from the EVM algebra: two disjoint regions A and B bound the
same faces exactly where they touch, so the faces they share are
``(area(A) + area(B) - area(A xor B)) / 2``, per axis. (For any two regions this counts the
faces on both boundaries: for segments of different layers that overlap, also the faces both
bound on the same side.)
"""

import csv
import io
import itertools

import numpy as np

from .._files import write_atomically
from . import _sweep
from ._volume import transform

FACE_ORDERS = ("xyz", "yzx", "zxy")
"""The key order whose planes hold the faces perpendicular to x, y and z."""

COLUMNS = ("label", "name", "voxels", "volume_mm3", "volume_ml", "area_mm2",
           "bbox_min_mm", "bbox_max_mm", "centroid_mm", "components")
"""The columns of :func:`write_measurements_csv`, in order."""


def face_counts(evm):
    """Unit boundary faces perpendicular to x, y and z (their sum is :meth:`EVM.area`)."""
    return tuple(int(_sweep.plane_area(evm.keys(order))) for order in FACE_ORDERS)


def faces_mm2(counts, spacing):
    """The physical area of ``counts`` voxel faces perpendicular to x, y and z (in this order of
    summation, whatever the machine)."""
    sx, sy, sz = spacing
    return float(int(counts[0]) * (sy * sz) + int(counts[1]) * (sx * sz)
                 + int(counts[2]) * (sx * sy))


def measure(vevm):
    """The exact measurements of a VolumeEVM's region; see the module docstring.

    Returns
    -------
    dict
        ``voxels``; ``volume_mm3`` and ``volume_ml`` (1 mL = 1000 mm³); ``area_mm2`` (the
        boundary's voxel faces); ``bbox_mm``: ``(min, max)`` corners of the axis-aligned box
        around the region's voxel corners in patient mm (LPS); ``centroid_mm`` (mean of the
        voxel centres, LPS mm); ``components`` (face-connected parts). Empty regions measure 0,
        with ``bbox_mm`` and ``centroid_mm`` None.
    """
    evm = vevm.evm
    voxel_mm3 = float(np.prod(vevm.spacing))
    voxels = vevm.voxel_count
    result = {"voxels": voxels, "volume_mm3": voxels * voxel_mm3,
              "volume_ml": voxels * voxel_mm3 / 1000.0,
              "area_mm2": faces_mm2(face_counts(evm), vevm.spacing),
              "bbox_mm": None, "centroid_mm": None, "components": 0}
    if evm.is_empty():
        return result
    lo, hi = evm.bounds()
    corners = np.array(list(itertools.product(*zip(lo, hi))), np.float64)
    corners = vevm.corner_positions(corners)
    box_lo, box_hi = evm.boxes()
    cells = np.prod(box_hi - box_lo, axis=1)
    # Twice the sum of the voxel centres, in integers (exact, in any order of summation).
    doubled = (cells[:, None] * (box_lo + box_hi - 1)).sum(axis=0)
    centre = doubled / (2.0 * voxels)  # voxel-centre index units
    matrix = vevm.index_to_physical()
    centroid = transform(centre[None], matrix[:3, :3].T, matrix[:3, 3])[0]
    result.update(bbox_mm=(tuple(corners.min(axis=0).tolist()),
                           tuple(corners.max(axis=0).tolist())),
                  centroid_mm=tuple(centroid.tolist()), components=len(evm.components()))
    return result


def measure_labels(regions):
    """:func:`measure` for every region of ``regions`` (``label -> VolumeEVM``, disjoint regions
    of one grid), each with ``shared_area_mm2``: :func:`shared_areas`' row for it."""
    shared = shared_areas(regions)
    return {label: {**measure(vevm), "shared_area_mm2": shared[label]}
            for label, vevm in regions.items()}


def shared_areas(regions):
    """The boundary area each pair of touching regions shares, in mm².

    Parameters
    ----------
    regions : dict
        ``label -> VolumeEVM``, disjoint regions of one grid (as
        :meth:`VolumeEVM.from_labels` makes them).

    Returns
    -------
    dict
        ``label -> {other label: mm²}``, only pairs that share faces, symmetric.
    """
    labels = list(regions)
    shared = {label: {} for label in labels}
    counts = {label: np.array(face_counts(regions[label].evm)) for label in labels}
    for a, b in itertools.combinations(labels, 2):
        ea, eb = regions[a].evm, regions[b].evm
        if ea.is_empty() or eb.is_empty() or not _touching(ea.bounds(), eb.bounds()):
            continue
        faces = (counts[a] + counts[b] - np.array(face_counts(ea ^ eb))) // 2
        if faces.any():
            shared[a][b] = shared[b][a] = faces_mm2(faces, regions[a].spacing)
    return shared


def _touching(a, b):
    """Whether two bounding boxes ``(lo, hi)`` overlap or touch (share at least a face)."""
    return all(alo <= bhi and blo <= ahi for alo, ahi, blo, bhi in zip(a[0], a[1], b[0], b[1]))


def write_measurements_csv(path, rows, *, overwrite=False):
    """Write measurement rows as CSV, atomically: one row per region, the columns of
    :data:`COLUMNS` (``label`` and ``name`` as the rows give them, points as ``x y z`` in mm);
    an existing file is replaced only with ``overwrite`` (see :meth:`LabelSet.write_measurements`).
    Returns the path written."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        bbox = row.get("bbox_mm") or (None, None)
        writer.writerow([row.get("label", ""), row.get("name", ""), row["voxels"],
                         f"{row['volume_mm3']:.6g}", f"{row['volume_ml']:.6g}",
                         f"{row['area_mm2']:.6g}", _point(bbox[0]), _point(bbox[1]),
                         _point(row.get("centroid_mm")), row["components"]])
    data = text.getvalue().encode("utf-8")

    def write(temporary):
        with open(temporary, "wb") as file:
            file.write(data)

    return write_atomically(path, write, overwrite=overwrite)


def _point(point):
    return "" if point is None else " ".join(f"{c:.6g}" for c in point)
