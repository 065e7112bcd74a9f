"""Import Volume's Read As in the real bpy: a segmentation NIfTI (the real liver label map) read
as a Label Map from the dialog is the label map a script gets with ``labels=True``; Densities
reads a Slicer segmentation's values; a label table names and colours the labels; a volume
that is no label map is refused with the core's message and the scene left as it was.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import bpy
import nibabel as nib
import numpy as np
import pytest

LIVER_LABELS = [84, 85, 127, 255]  # the data README's labels, 0 (background) left out


@pytest.fixture(scope="module")
def liver_nii(data_dir, tmp_path_factory):
    """The real liver label map (uint8) as a NIfTI file, its spacing in the header."""
    array = np.load(data_dir / "seg_liver_cgal.npy")
    spacing = (0.617, 0.617, 1.333)
    path = tmp_path_factory.mktemp("liver") / "liver_labels.nii.gz"
    nib.save(nib.Nifti1Image(array, np.diag([*spacing, 1.0])), str(path))
    return path


def _rows(obj):
    return [(row.label, row.name, tuple(row.color)) for row in obj.volumeevm.labels]


def _objects():
    return sorted(o.name for o in bpy.data.objects)


def test_a_segmentation_nifti_read_as_a_label_map(ext, api, core, liver_nii):
    assert api.import_volume(liver_nii).volumeevm.label_count == 0  # Automatic: densities
    assert bpy.ops.volumeevm.import_volume(filepath=str(liver_nii), name="op",
                                           read_as="LABELS") == {"FINISHED"}
    op = bpy.data.objects["op"]
    script = api.import_volume(liver_nii, name="script", labels=True)
    assert op.volumeevm.label_count == script.volumeevm.label_count == len(LIVER_LABELS)
    assert [row[0] for row in _rows(op)] == LIVER_LABELS
    assert _rows(op) == _rows(script)
    assert op.volumeevm.threshold == script.volumeevm.threshold == LIVER_LABELS[0]
    runtime = ext.blender.runtime
    got, want = runtime.volume(op.volumeevm.uid), runtime.volume(script.volumeevm.uid)
    assert got.labels == want.labels == core.read_volume(liver_nii, labels=True).labels
    np.testing.assert_array_equal(got.array, want.array)
    # Build reads the file again as the object was imported: still a label map.
    runtime.forget_except(set())
    assert runtime.volume(op.volumeevm.uid) is None
    api.build(op)
    assert runtime.volume(op.volumeevm.uid).labels == want.labels


def test_densities_read_a_slicer_segmentation_as_values(api, data_dir):
    path = data_dir / "slicer" / "Segmentation.seg.nrrd"
    assert bpy.ops.volumeevm.import_volume(filepath=str(path), name="auto") == {"FINISHED"}
    assert bpy.data.objects["auto"].volumeevm.label_count == 7  # what the file says
    assert bpy.ops.volumeevm.import_volume(filepath=str(path), name="values",
                                           read_as="DENSITIES") == {"FINISHED"}
    values = bpy.data.objects["values"]
    assert values.volumeevm.label_count == 0 and len(values.volumeevm.labels) == 0
    script = api.import_volume(path, labels=False)
    assert values.volumeevm.value_min == script.volumeevm.value_min
    assert values.volumeevm.value_max == script.volumeevm.value_max
    assert list(values.volumeevm.histogram) == list(script.volumeevm.histogram)


@pytest.mark.parametrize("kind", ["txt", "json"])
def test_a_label_table_names_and_colours_the_labels(core, liver_nii, tmp_path, kind):
    names = ["liver", "portal vein", "hepatic vein", "tumour"]
    rgb = [(200, 100, 50), (0, 0, 255), (10, 200, 30), (255, 255, 0)]
    table = tmp_path / f"liver_labels.{kind}"
    if kind == "txt":  # ITK-SNAP's label description, as ITK-SNAP writes it
        lines = ["# ITK-SnAP Label Description File",
                 '    0     0    0    0        0  0  0    "Clear Label"']
        lines += [f'{label:5d} {r:5d} {g:4d} {b:4d}        1  1  1    "{name}"'
                  for label, name, (r, g, b) in zip(LIVER_LABELS, names, rgb)]
        table.write_text("\n".join(lines) + "\n")
    else:
        import json

        table.write_text(json.dumps({str(label): {"name": name, "color": list(c)}
                                     for label, name, c in zip(LIVER_LABELS, names, rgb)}))
    assert bpy.ops.volumeevm.import_volume(filepath=str(liver_nii), read_as="LABELS",
                                           label_table=str(table)) == {"FINISHED"}
    obj = bpy.context.active_object
    assert [(row.label, row.name) for row in obj.volumeevm.labels] == list(
        zip(LIVER_LABELS, names))
    for row, c in zip(obj.volumeevm.labels, rgb):
        assert tuple(row.color) == pytest.approx([v / 255.0 for v in c], abs=1e-6)
    want = core.read_volume(liver_nii, labels=table).labels
    assert {row.label: row.name for row in obj.volumeevm.labels} == {
        label: info.name for label, info in want.items()}


def test_a_float_ct_read_as_a_label_map_is_refused_and_nothing_changes(api, data_dir):
    api.import_volume(data_dir / "slicer" / "CTChest4.nrrd")  # something to keep
    before = _objects(), len(bpy.data.meshes)
    skull = data_dir / "ct_skull_cgal.npy"  # float32 densities
    with pytest.raises(RuntimeError, match="ct_skull_cgal.npy: a label map must hold integers, "
                                           "got dtype float32"):
        bpy.ops.volumeevm.import_volume(filepath=str(skull), read_as="LABELS")
    assert (_objects(), len(bpy.data.meshes)) == before
    # A CT in HU has negative values: no label map either, and the message says how many.
    with pytest.raises(RuntimeError, match="CTChest4.nrrd: a label map holds labels >= 0"):
        bpy.ops.volumeevm.import_volume(filepath=str(data_dir / "slicer" / "CTChest4.nrrd"),
                                        read_as="LABELS")
    assert (_objects(), len(bpy.data.meshes)) == before


def test_a_bad_label_table_is_refused_naming_it(liver_nii, tmp_path):
    table = tmp_path / "bad.txt"
    table.write_text('84 300 0 0 1 1 1 "liver"\n')
    with pytest.raises(RuntimeError, match=r"bad.txt: line 1: R G B must be integers in 0..255"):
        bpy.ops.volumeevm.import_volume(filepath=str(liver_nii), read_as="LABELS",
                                        label_table=str(table))
    assert _objects() == []
