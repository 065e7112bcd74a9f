"""Label maps among the files: a volume marked as a segmentation, with its labels' names and
colours (:mod:`volumeevm_addon.model._label_table`)."""

import dataclasses

from ..model._label_table import label_table_for, read_label_table
from ..model._labels import labels_present


def label_map(volume, table=None):
    """``volume`` as a label map: ``labels`` holds every present label's name and colour, from
    ``table`` (``label -> LabelInfo``) where it names them, from the palette otherwise.

    Raises
    ------
    VolumeEVMError
        If the data is not a label map (integers >= 0), naming the file.

    Warns
    -----
    UserWarning
        For labels the table names but the data lacks, or the data has but the table lacks.
    """
    source = volume.source or "volume"
    present = set()
    for layer in volume.layers or (volume.array,):
        present.update(labels_present(layer, source).tolist())
    return dataclasses.replace(volume, labels=label_table_for(present, table, source=source))


def as_label_map(volume, labels):
    """What ``read_volume(..., labels=)`` asks of the volume read: ``None`` keeps what the file
    says, ``False`` reads densities, ``True`` a label map (with the file's names and colours
    when it is one, else the palette's), a path a label map named by that label table
    (ITK-SNAP ``.txt`` or JSON)."""
    if labels is None or (labels is True and volume.is_label_map):
        return volume
    if labels is False:  # a segmentation in layers: their overlay
        return dataclasses.replace(volume, labels=None, layers=None)
    return label_map(volume, None if labels is True else read_label_table(labels))
