"""Label maps in Blender: one named, coloured mesh object per label, or one mesh with a material
per label.

:func:`make_label_meshes` reads the volume object's label map (a 3D Slicer ``.seg.nrrd`` brings
its segments' names and colours; any other integer volume is named and coloured by the core's
fixed palette), builds every label's VolumeEVM in one sweep (:meth:`VolumeEVM.from_labels`) and
makes each label's exact closed mesh, all together (:meth:`LabelSet.meshes`): where two labels
touch, their meshes carry the same polygons, reversed: no gap, no overlap, no T-junction.

- By default each label is its own mesh object, named after the label, with a material of the
  label's colour, all children of one empty (itself a child of the volume object, so moving the
  box moves them) in a collection ``"<volume> labels"``: select, hide or export each structure.
- ``single_mesh=True`` makes one mesh object instead, a material slot per label and the integer
  face attribute ``label`` holding each face's label (for Geometry Nodes, or one file to print
  in colour).

Making them again replaces the objects of the collection. Whatever the error, the scene stays as
it was (:func:`.jobs.transaction`).
"""

import bpy
import numpy as np

from ..volumeevm_addon import VolumeEVM, VolumeEVMError
from ..volumeevm_addon.model import Polygons
from . import jobs, tool_stack
from .meshes import Faces, fill_mesh, label_geometry
from .objects import volume_object
from .volumes import read_steps, source_of


def _label_steps(uid, path, options, manifold):
    volume = yield from read_steps(uid, path, options)
    yield 0.2, "building every label"
    regions = VolumeEVM.from_labels(volume)  # refused, naming the file, unless integers >= 0
    yield 0.4, f"meshing {len(regions)} labels"
    meshes = [(label, co, faces)
              for label, (co, faces) in label_geometry(regions, manifold).items()]
    return regions.infos, meshes


def _material(name, color):
    """A material of ``color`` (RGB 0..1) for the viewport and the renderers."""
    material = bpy.data.materials.new(name)
    material.diffuse_color = (*color, 1.0)
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True  # always on (and deprecated) from 5.0
    material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (*color, 1.0)
    return material


def _remove_replaced(collection):
    """Remove a replaced collection, its objects, and their meshes and materials that nothing
    else uses."""
    objects = list(collection.objects)
    data = {o.data for o in objects if o.data is not None}
    materials = {m for mesh in data for m in mesh.materials if m is not None}
    bpy.data.batch_remove(objects + [collection])
    bpy.data.batch_remove([mesh for mesh in data if mesh.users == 0])
    bpy.data.batch_remove([material for material in materials if material.users == 0])


def _joined(meshes):
    """The label meshes as one vertex array and one :class:`.meshes.Faces`, and each face's
    label."""
    co, indices, starts, sizes, edges, corner_edges, labels = [], [], [], [], [], [], []
    vertices = loops = edge_count = 0
    for label, mesh_co, faces in meshes:
        polygons = faces.polygons
        co.append(mesh_co)
        indices.append(polygons.indices + vertices)
        starts.append(polygons.starts + loops)
        sizes.append(polygons.sizes)
        edges.append(faces.edges + vertices)
        corner_edges.append(faces.corner_edges + edge_count)
        labels.append(np.full(len(polygons), label, np.int32))
        vertices += len(mesh_co)
        loops += len(polygons.indices)
        edge_count += len(faces.edges)
    faces = Faces(Polygons(*(np.concatenate(a).astype(np.int32) for a in (indices, starts, sizes))),
                  np.concatenate(edges).astype(np.int32),
                  np.concatenate(corner_edges).astype(np.int32))
    return np.concatenate(co), faces, np.concatenate(labels)


def label_meshes_job(context, obj, *, single_mesh=False, manifold=False):
    """The label-meshes job (see :func:`make_label_meshes`)."""
    vol_obj = volume_object(obj)
    name = vol_obj.name
    path, options = source_of(vol_obj)

    def commit(result):
        infos, meshes = result
        owner = bpy.data.objects.get(name)
        if owner is None:
            raise VolumeEVMError(f"{name}: the volume object was deleted while meshing")
        collection_name = f"{name} labels"
        old = bpy.data.collections.get(collection_name)
        if old is not None:  # made again: the new objects replace the old ones
            jobs.on_success(lambda: _remove_replaced(old))
            old.name = f"{collection_name} (replaced)"
            jobs.on_undo(lambda: setattr(old, "name", collection_name))
        collection = bpy.data.collections.new(collection_name)
        (context.collection or context.scene.collection).children.link(collection)
        parent = bpy.data.objects.new(collection_name, None)
        parent.parent = owner
        collection.objects.link(parent)
        materials = {label: _material(f"{name} {infos[label].name}", infos[label].color)
                     for label, _, _ in meshes}
        made = []
        if single_mesh:
            co, faces, labels = _joined(meshes)
            mesh = bpy.data.meshes.new(f"{name} labels")
            fill_mesh(mesh, co, faces)
            values = np.array([label for label, _, _ in meshes])  # increasing: slot = place
            for label in values:
                mesh.materials.append(materials[label])
            mesh.polygons.foreach_set("material_index",
                                      np.searchsorted(values, labels).astype(np.int32))
            mesh.attributes.new("label", "INT", "FACE").data.foreach_set("value", labels)
            made.append(bpy.data.objects.new(f"{name} labels mesh", mesh))
        else:
            for label, co, faces in meshes:
                mesh = bpy.data.meshes.new(infos[label].name)
                fill_mesh(mesh, co, faces)
                mesh.materials.append(materials[label])
                made.append(bpy.data.objects.new(infos[label].name, mesh))
                made[-1].color = (*infos[label].color, 1.0)  # the viewport's object colour
                made[-1]["volumeevm_label"] = int(label)
        for child in made:
            child.parent = parent
            collection.objects.link(child)
        return made

    return jobs.Job(f"Label meshes of {name}",
                    _label_steps(vol_obj.volumeevm.uid, path, options, manifold), commit)


def make_label_meshes(obj, *, single_mesh=False, manifold=False):
    """Make a named, coloured mesh object per label of a volume object's label map.

    Parameters
    ----------
    obj : bpy.types.Object
        A volume object whose data is a label map (integers, 0 = background).
    single_mesh : bool, optional
        One mesh object with a material per label and the face attribute ``label`` instead of
        one object per label.

    Returns
    -------
    list of bpy.types.Object
        The label objects (or the one mesh object), in increasing label order, children of an
        empty in the collection ``"<volume> labels"``.

    Raises
    ------
    VolumeEVMError
        Not a volume object, a volume that is not a label map (names the file), a source file
        that is gone.
    """
    return jobs.run(label_meshes_job(bpy.context, obj, single_mesh=single_mesh, manifold=manifold))


# ---------------------------------------------------------------------- measurements
SMOOTH_AREA_NOTE = ("Exact for the voxel model: volume = voxels × voxel volume, area = the voxel "
                    "faces. A smooth surface through the voxels has less area: the faces' area "
                    "is the smooth area × (|nx|+|ny|+|nz|), 1 to 1.73, 1.5 on average (a sphere)")
"""What the measurements are, shown beside them (see :meth:`VolumeEVM.measure`)."""


def _measure_steps(uid, path, options):
    volume = yield from read_steps(uid, path, options)
    yield 0.2, "building every label"
    regions = VolumeEVM.from_labels(volume)
    rows = []
    for number, (label, region) in enumerate(regions.items()):
        yield 0.3 + 0.7 * number / len(regions), f"measuring {regions.infos[label].name}"
        rows.append((label, regions.infos[label], region.measure()))
    return rows


def measure_job(context, obj):
    """The measurements job (see :func:`measure_labels`)."""
    vol_obj = volume_object(obj)
    name = vol_obj.name
    path, options = source_of(vol_obj)

    def commit(rows):
        owner = bpy.data.objects.get(name)
        if owner is None:
            raise VolumeEVMError(f"{name}: the volume object was deleted while measuring")
        table = owner.volumeevm.label_measurements
        table.clear()
        for label, info, row in rows:
            item = table.add()
            item.label, item.name, item.color = label, info.name, info.color
            item.voxels = float(row["voxels"])
            item.volume_ml, item.area_mm2 = row["volume_ml"], row["area_mm2"]
            item.components = row["components"]
        owner.volumeevm.label_measurement_index = -1
        return rows

    return jobs.Job(f"Measurements of {name}", _measure_steps(vol_obj.volumeevm.uid, path, options),
                    commit)


def measure_labels(obj):
    """Measure every label of a volume object's label map and list them in its sidebar.

    Parameters
    ----------
    obj : bpy.types.Object
        A volume object whose data is a label map.

    Returns
    -------
    list of tuple
        ``(label, LabelInfo, VolumeEVM.measure() dict)`` per label, in increasing label order;
        the volume object's ``volumeevm.label_measurements`` holds the same rows.

    Raises
    ------
    VolumeEVMError
        Not a volume object, not a label map (names the file), a source file that is gone.
    """
    return jobs.run(measure_job(bpy.context, obj))


def _export_steps(uid, path, options, csv_path, overwrite):
    volume = yield from read_steps(uid, path, options)
    yield 0.2, "building every label"
    regions = VolumeEVM.from_labels(volume)
    yield 0.5, "measuring every label"
    return regions.write_measurements(csv_path, overwrite=overwrite)


def export_measurements_job(context, obj, csv_path, *, overwrite=False):
    """The CSV export job (see :func:`export_label_measurements`)."""
    vol_obj = volume_object(obj)
    path, options = source_of(vol_obj)
    csv_path = bpy.path.abspath(str(csv_path))
    return jobs.Job(f"Measurements of {vol_obj.name} to CSV",
                    _export_steps(vol_obj.volumeevm.uid, path, options, csv_path, overwrite),
                    lambda written: written)


def export_label_measurements(obj, csv_path, *, overwrite=False):
    """Write every label's exact measurements as CSV (:meth:`LabelSet.write_measurements`).

    Parameters
    ----------
    obj : bpy.types.Object
        A volume object whose data is a label map.
    csv_path : str or os.PathLike
        The file (``//`` = beside the .blend), written atomically.
    overwrite : bool, optional
        Replace an existing file (default False: an existing file is an error).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    VolumeEVMError
        Not a label map, the file exists and ``overwrite`` is False, or it cannot be written.
    """
    return jobs.run(export_measurements_job(bpy.context, obj, csv_path, overwrite=overwrite))


def select_label(context, vol_obj, label):
    """Select the label's object alone and make it active (nothing when it has none); the
    sidebar keeps showing its volume (:func:`.objects.active_volume`)."""
    obj = tool_stack.label_objects(vol_obj).get(label)
    if obj is None or obj.name not in context.view_layer.objects:
        return None
    for other in context.view_layer.objects.selected:
        other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    return obj
