"""Label names and colours: Slicer's segment keys, ITK-SNAP's label description and JSON
sidecars read exactly or refused by name, and disagreements with the data reported."""

import json
import warnings

import nrrd
import numpy as np
import pytest

from reader_files import write_nrrd
from volumeevm_addon import VolumeEVM, VolumeEVMError, read_volume
from volumeevm_addon.model import LabelInfo
from volumeevm_addon.model._label_table import (
    default_label_info,
    label_table_for,
    palette_color,
    read_label_table,
    slicer_segments,
)

ITKSNAP = '''################################################
# ITK-SnAP Label Description File
#    IDX   -R-  -G-  -B-  -A--  VIS MSH  LABEL
################################################
    0     0    0    0        0  0  0    "Clear Label"
    1   255    0    0        1  1  1    "Liver"
    7     0  128  255      0.5  1  0    "Portal vein (main)"
'''


def test_slicer_segments_of_the_real_files(data_dir):
    header = nrrd.read_header(str(data_dir / "slicer" / "Segmentation.seg.nrrd"))
    segments = slicer_segments(header, "Segmentation.seg.nrrd")
    names = [s["name"] for s in segments]
    assert names[:2] == ["ribs", "cervical vertebral column"] and len(set(names)) == len(names)
    assert all(s["layer"] == 0 for s in segments)
    assert [s["value"] for s in segments] == list(range(1, len(segments) + 1))
    assert segments[0]["color"] == (0.992157, 0.909804, 0.619608)
    overlapping = slicer_segments(
        nrrd.read_header(str(data_dir / "slicer" / "SegmentationOverlapping.seg.nrrd")),
        "SegmentationOverlapping.seg.nrrd")
    assert overlapping[-1] == {"id": overlapping[-1]["id"], "name": "overlapping sphere",
                               "color": (0.862745, 0.960784, 0.0784314), "layer": 1, "value": 1}
    assert {(s["layer"], s["value"]) for s in overlapping[:-1]} == {(0, v) for v in range(1, 8)}


def _header(**changes):
    header = {"Segment0_ID": "a", "Segment0_Name": "liver", "Segment0_Color": "1 0 0",
              "Segment0_LabelValue": "1", "Segment0_Layer": "0",
              "Segment1_ID": "b", "Segment1_Name": "vein", "Segment1_Color": "0 0 1",
              "Segment1_LabelValue": "2", "Segment1_Layer": "0"}
    header.update(changes)
    return {k: v for k, v in header.items() if v is not None}


@pytest.mark.parametrize("changes, message", [
    ({"Segment1_Name": "liver"}, "Segment1: name 'liver' is also segment 0's"),
    ({"Segment1_LabelValue": "1"}, "Segment1: layer 0, label value 1 is also segment 0's"),
    ({"Segment1_Color": "0 0"}, "Segment1_Color: colour .* is not three numbers"),
    ({"Segment1_Color": "red"}, "Segment1_Color: colour 'red' is not '#rrggbb'"),
    ({"Segment1_Color": "0 0 300"}, "neither three numbers in 0..1 nor three integers"),
    ({"Segment1_LabelValue": "two"}, "Segment1: LabelValue and Layer must be integers"),
    ({"Segment1_LabelValue": "0"}, "LabelValue must be > 0"),
    ({"Segment1_Layer": None}, "segment 1 has no Segment1_Layer"),
])
def test_bad_slicer_segment_keys_are_refused_by_name(changes, message):
    with pytest.raises(VolumeEVMError, match="^x.seg.nrrd: .*" + message):
        slicer_segments(_header(**changes), "x.seg.nrrd")


def test_itksnap_and_json_tables(tmp_path):
    path = tmp_path / "labels.txt"
    path.write_text(ITKSNAP)
    table = read_label_table(path)
    assert table == {1: LabelInfo("Liver", (1.0, 0.0, 0.0)),
                     7: LabelInfo("Portal vein (main)", (0.0, 128 / 255, 1.0))}
    sidecar = tmp_path / "labels.json"
    sidecar.write_text(json.dumps({"1": {"name": "Liver", "color": "#ff0000"},
                                   "7": {"name": "Portal vein (main)", "color": [0, 128, 255]},
                                   "9": {"name": "spleen", "color": [0.5, 0.25, 1.0]}}))
    assert read_label_table(sidecar) == {**table, 9: LabelInfo("spleen", (0.5, 0.25, 1.0))}


@pytest.mark.parametrize("name, text, message", [
    ("t.txt", '  1 255 0 0 1 1 1 "A"\n  1 0 0 255 1 1 1 "B"\n', "line 2: label 1 is named twice"),
    ("t.txt", '  1 255 0 0 1 1 "A"\n', "line 1: an ITK-SNAP label line has 8 fields"),
    ("t.txt", '  1 256 0 0 1 1 1 "A"\n', "line 1: R G B must be integers in 0..255"),
    ("t.txt", '  x 25 0 0 1 1 1 "A"\n', "line 1: label 'x' is not an integer >= 0"),
    ("t.txt", '  1 25 0 0 1 1 1 "A\n', "line 1: No closing quotation"),
    ("t.json", '{"1": {"name": "A"}}', "label '1': an entry needs 'name' and 'color'"),
    ("t.json", '{"1": {"name": "", "color": "#000000"}}', "label 1 has no name"),
    ("t.json", '{"-3": {"name": "A", "color": "#000000"}}', "is not an integer >= 0"),
    ("t.json", '[1, 2]', "a label table is an object"),
    ("t.json", '{"1": ', "not valid JSON"),
    ("t.json", '{"1": {"name": "A", "color": [1, 2]}}', "colour \\[1, 2\\] is not three numbers"),
])
def test_bad_tables_are_refused_naming_the_file_and_line(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(VolumeEVMError, match=f"^{path}: .*{message}"):
        read_label_table(path)


def test_disagreements_with_the_data_are_reported_not_silent():
    table = {1: LabelInfo("Liver", (1.0, 0.0, 0.0)), 5: LabelInfo("Lesion", (0.0, 1.0, 0.0))}
    with pytest.warns(UserWarning) as caught:
        merged = label_table_for([0, 1, 2], table, source="seg.nii")
    messages = [str(w.message) for w in caught]
    assert "seg.nii: the label table names labels the data does not have: [5]" in messages
    assert ("seg.nii: labels [2] are not in the label table; they get the default names and "
            "colours") in messages
    assert merged == {1: table[1], 2: default_label_info(2)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert label_table_for(np.array([3, 0, 1])) == {1: default_label_info(1),
                                                       3: default_label_info(3)}


def test_the_palette_is_fixed_and_tells_neighbours_apart():
    colors = [palette_color(label) for label in range(1, 101)]
    assert palette_color(17) == palette_color(np.int64(17))  # the same on every call and type
    assert all(0.0 <= c <= 1.0 for rgb in colors for c in rgb)
    for a, b in zip(colors, colors[1:]):
        assert max(abs(x - y) for x, y in zip(a, b)) > 0.15  # neighbouring labels differ
    assert len(set(colors)) == 100


# ---------------------------------------------------------------------- read_volume(labels=)
def test_a_slicer_segmentation_reads_as_named_coloured_labels(data_dir):
    path = data_dir / "slicer" / "Segmentation.seg.nrrd"
    volume = read_volume(path)
    header = nrrd.read_header(str(path))
    segments = slicer_segments(header, str(path))
    assert volume.is_label_map
    assert volume.labels == {s["value"]: LabelInfo(s["name"], s["color"]) for s in segments}
    data, _ = nrrd.read(str(path))
    assert np.array_equal(volume.array, data)
    regions = VolumeEVM.from_labels(volume)
    assert regions.infos == volume.labels
    for label, region in regions.items():
        assert region.evm == VolumeEVM.from_array(data, label, upper=label).evm
    assert not read_volume(path, labels=False).is_label_map


def test_a_segmentation_in_layers_reads_every_segment_as_its_own_exact_label(data_dir):
    path = data_dir / "slicer" / "SegmentationOverlapping.seg.nrrd"
    data, header = nrrd.read(str(path))
    segments = slicer_segments(header, str(path))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every segment has voxels, every value a segment
        volume = read_volume(path)
    assert data.shape == (2, 128, 128, 34) and volume.shape == (128, 128, 34)
    # Layer 0 keeps its values 1..7; layer 1's value 1 moves past them: label 8.
    labels = {s["value"] + 7 * s["layer"]: LabelInfo(s["name"], s["color"]) for s in segments}
    assert volume.labels == labels and volume.labels[8].name == "overlapping sphere"
    assert len(volume.layers) == 2
    assert np.array_equal(volume.layers[0], data[0])
    assert np.array_equal(volume.layers[1], np.where(data[1] > 0, data[1] + 7, 0))
    overlay = np.where(data[1] > 0, 8, data[0])  # the later layer over the earlier
    assert np.array_equal(volume.array, overlay)
    reference = read_volume(data_dir / "slicer" / "Segmentation.seg.nrrd")
    assert volume.spacing == reference.spacing and volume.origin == reference.origin
    assert np.array_equal(volume.orientation, reference.orientation)
    regions = VolumeEVM.from_labels(volume)
    assert list(regions) == list(range(1, 9)) and regions.infos == labels
    for s in segments:
        label = s["value"] + 7 * s["layer"]
        exact = VolumeEVM.from_array(data[s["layer"]], s["value"], upper=s["value"]).evm
        assert regions[label].evm == exact  # every segment an exact solid
        assert regions[label].voxel_count == np.count_nonzero(data[s["layer"]] == s["value"])
        assert (regions[label].table(0) == label).all()
    # The sphere shares voxels with the labels of layer 0 (the reason for layers).
    inside = data[0][data[1] == 1]
    assert (regions[8].evm & regions[7].evm).volume() == np.count_nonzero(inside == 7) > 0
    assert (regions[8].evm & regions[5].evm).volume() == np.count_nonzero(inside == 5) > 0
    picked = VolumeEVM.from_labels(volume, labels=[2, 8])
    assert list(picked) == [2, 8] and picked[8].evm == regions[8].evm
    assert not read_volume(path, labels=False).is_label_map


def _layered_file(tmp_path, data, segments):
    """A two-layer .seg.nrrd written by pynrrd with ``segments``: (name, colour, layer, value)."""
    header = {"kinds": ["list", "domain", "domain", "domain"], "space": "left-posterior-superior",
              "space directions": [[np.nan] * 3, [1.0, 0, 0], [0, 1.0, 0], [0, 0, 2.0]],
              "space origin": [0.0, 0.0, 0.0], "encoding": "raw"}
    for n, (name, color, layer, value) in enumerate(segments):
        header.update({f"Segment{n}_ID": f"s{n}", f"Segment{n}_Name": name,
                       f"Segment{n}_Color": color, f"Segment{n}_LabelValue": str(value),
                       f"Segment{n}_Layer": str(layer)})
    path = tmp_path / "x.seg.nrrd"
    write_nrrd(path, data, header)
    return path


def test_a_layered_segmentation_that_disagrees_with_its_data_is_reported(tmp_path):
    data = np.zeros((2, 4, 5, 6), np.uint8)
    data[0, :2] = 1
    data[0, 2:, :2] = 3  # a value no segment describes
    data[1, 1:3, 1:4] = 1
    good = [("bone", "1 1 1", 0, 1), ("vessel", "1 0 0", 0, 2), ("tumour", "0 1 0", 1, 1)]
    path = _layered_file(tmp_path, data, good)
    with pytest.warns(UserWarning) as caught:
        volume = read_volume(path)
    assert sorted(str(w.message) for w in caught) == [
        f"{path}: layer 0 holds label values [3] that no segment describes; they get labels [3] "
        f"with the default names and colours",
        f"{path}: segments 'vessel' (layer 0, label value 2) have no voxels in the data"]
    # Layer 1 moves past layer 0's highest value in the header or the data (3).
    assert volume.labels == {1: LabelInfo("bone", (1.0, 1.0, 1.0)), 3: default_label_info(3),
                             4: LabelInfo("tumour", (0.0, 1.0, 0.0))}
    assert VolumeEVM.from_labels(volume)[4].voxel_count == 2 * 3 * 6
    for segments, message in [
        (good[:2] + [("bone", "0 1 0", 1, 1)], "Segment2: name 'bone' is also segment 0's"),
        (good[:2] + [("tumour", "0 1", 1, 1)], "Segment2_Color: colour .* is not three numbers"),
        (good[:2] + [("tumour", "green", 1, 1)], "Segment2_Color: colour 'green'"),
        (good[:2] + [("tumour", "0 1 0", 2, 1)], r"segments \['tumour'\] are in layers the data "
                                                  r"does not have \(it has 2\)"),
    ]:
        path = _layered_file(tmp_path, data, segments)
        with pytest.raises(VolumeEVMError, match=f"^{path}: .*{message}"):
            read_volume(path)


def test_a_label_map_with_its_table_or_the_palette(tmp_path, data_dir):
    array = np.load(data_dir / "seg_liver_cgal.npy")
    np.save(tmp_path / "liver.npy", array)
    table = tmp_path / "liver.txt"
    table.write_text('  84 255 0 0 1 1 1 "vessel"\n  85 0 255 0 1 1 1 "tumour"\n'
                     ' 127 0 0 255 1 1 1 "liver"\n 255 255 255 0 1 1 1 "body"\n')
    volume = read_volume(tmp_path / "liver.npy", labels=table)
    assert volume.is_label_map and [i.name for i in volume.labels.values()] == [
        "vessel", "tumour", "liver", "body"]
    assert volume.labels[127].color == (0.0, 0.0, 1.0)
    plain = read_volume(tmp_path / "liver.npy", labels=True)
    assert plain.labels == {label: default_label_info(label) for label in (84, 85, 127, 255)}
    assert not read_volume(tmp_path / "liver.npy").is_label_map
    table.write_text(' 127 0 0 255 1 1 1 "liver"\n 300 9 9 9 1 1 1 "spleen"\n')
    with pytest.warns(UserWarning) as caught:
        read_volume(tmp_path / "liver.npy", labels=table)
    assert {str(w.message).split(": ", 1)[1] for w in caught} == {
        "the label table names labels the data does not have: [300]",
        "labels [84, 85, 255] are not in the label table; they get the default names and colours"}


def test_what_is_not_a_label_map_is_refused_when_read_as_one(data_dir):
    with pytest.raises(VolumeEVMError, match=r"CTChest4.nrrd: a label map holds labels >= 0"):
        read_volume(data_dir / "slicer" / "CTChest4.nrrd", labels=True)
    with pytest.raises(VolumeEVMError,
                       match=r"labels: 3 is not True, False, None or a label table"):
        read_volume(data_dir / "slicer" / "CTChest4.nrrd", labels=3)
