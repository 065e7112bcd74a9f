"""What a label map's labels are called and how they look: names and colours from the file.

Segmentation tools keep their label names and colours in three places this module reads:

- 3D Slicer's ``.seg.nrrd`` header: ``SegmentN_Name``, ``SegmentN_Color`` (three numbers in
  0..1), ``SegmentN_LabelValue`` and ``SegmentN_Layer`` for each segment N
  (:func:`slicer_segments`);
- ITK-SNAP's label description file (``.txt``: ``IDX R G B A VIS MSH "LABEL"`` per line, colours
  in 0..255) and a JSON sidecar ``{"label": {"name": ..., "color": ...}}`` (colour as three
  numbers in 0..1, three integers in 0..255, or ``"#rrggbb"``) (:func:`read_label_table`).

Labels no table names get a name ``"label L"`` and a colour from a fixed categorical palette
(:func:`palette_color`): the same label always gets the same colour, on every machine.
Disagreements between a table and the data are never silent: a table that names labels the
volume lacks, or a volume with labels the table lacks, is reported in a warning naming them
(:func:`label_table_for`); malformed entries are a :class:`VolumeEVMError` naming the file and
the line or key.
"""

import colorsys
import json
import math
import re
import shlex
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError


@dataclass(frozen=True)
class LabelInfo:
    """A label's name and display colour.

    Attributes
    ----------
    name : str
        As the segmentation tool named it (``"label L"`` when nothing did).
    color : tuple of 3 float
        Display RGB (sRGB) in 0..1, as the tool stored it.
    """

    name: str
    color: tuple


_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def palette_color(label):
    """A label's colour when no table gives one: hues a golden-ratio turn apart per label, so
    neighbouring numbers look different; the same label gives the same colour everywhere."""
    hue = (int(label) * _GOLDEN) % 1.0
    value = 0.95 if int(label) % 2 else 0.8
    return tuple(round(c, 6) for c in colorsys.hsv_to_rgb(hue, 0.65, value))


def default_label_info(label):
    """:class:`LabelInfo` of a label no table names."""
    return LabelInfo(f"label {int(label)}", palette_color(label))


def _color(value, where):
    """An RGB colour in 0..1 from three numbers in 0..1, three integers in 0..255 or
    ``"#rrggbb"``; anything else is a VolumeEVMError naming ``where``."""
    if isinstance(value, str):
        match = re.fullmatch(r"#([0-9a-fA-F]{6})", value.strip())
        if not match:
            raise VolumeEVMError(f"{where}: colour {value!r} is not '#rrggbb' or three numbers")
        return tuple(int(match.group(1)[i:i + 2], 16) / 255.0 for i in (0, 2, 4))
    try:
        rgb = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        rgb = np.zeros(0)
    if rgb.shape != (3,) or not np.isfinite(rgb).all() or (rgb < 0).any():
        raise VolumeEVMError(f"{where}: colour {value!r} is not three numbers >= 0")
    if (rgb > 1).any():  # 0..255
        if (rgb > 255).any() or (rgb != np.round(rgb)).any():
            raise VolumeEVMError(f"{where}: colour {value!r} is neither three numbers in 0..1 nor "
                                 f"three integers in 0..255")
        rgb = rgb / 255.0
    return tuple(float(c) for c in rgb)


def read_label_table(path):
    """Label names and colours from an ITK-SNAP label description (``.txt``) or a JSON sidecar.

    Parameters
    ----------
    path : str or os.PathLike
        The table; ``.json`` is read as ``{"label": {"name": str, "color": colour}}``, any other
        suffix as ITK-SNAP's text format. Label 0 (ITK-SNAP's "Clear Label") is the background
        and left out.

    Returns
    -------
    dict
        ``label (int) -> LabelInfo``.

    Raises
    ------
    VolumeEVMError
        If the file cannot be read, or an entry is malformed (naming the file and the line or
        key): a label that is not an integer >= 0 or appears twice, a missing name, a bad colour.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise VolumeEVMError(f"{path}: cannot read the label table ({error})") from error
    entries = (_json_entries(text, path) if path.suffix.lower() == ".json"
               else _itksnap_entries(text, path))
    table = {}
    for where, text_label, name, color in entries:
        if not re.fullmatch(r"\s*\d+\s*", text_label):
            raise VolumeEVMError(f"{where}: label {text_label!r} is not an integer >= 0")
        label = int(text_label)
        if label in table:
            raise VolumeEVMError(f"{where}: label {label} is named twice")
        if not isinstance(name, str) or not name.strip():
            raise VolumeEVMError(f"{where}: label {label} has no name")
        table[label] = LabelInfo(name.strip(), _color(color, where))
    table.pop(0, None)
    return table


def _json_entries(text, path):
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise VolumeEVMError(f"{path}: not valid JSON ({error})") from error
    if not isinstance(data, dict):
        raise VolumeEVMError(f"{path}: a label table is an object {{label: {{name, color}}}}")
    for key, entry in data.items():
        where = f"{path}: label {key!r}"
        if not isinstance(entry, dict) or "name" not in entry or "color" not in entry:
            raise VolumeEVMError(f"{where}: an entry needs 'name' and 'color'")
        yield where, key, entry["name"], entry["color"]


def _itksnap_entries(text, path):
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        where = f"{path}: line {number}"
        try:
            fields = shlex.split(line)
        except ValueError as error:
            raise VolumeEVMError(f"{where}: {error}") from error
        if len(fields) != 8:
            raise VolumeEVMError(f"{where}: an ITK-SNAP label line has 8 fields (IDX R G B A VIS "
                                 f"MSH \"LABEL\"), got {len(fields)}")
        try:
            rgb = [int(f) for f in fields[1:4]]
        except ValueError as error:
            raise VolumeEVMError(f"{where}: R G B must be integers in 0..255") from error
        if any(not 0 <= c <= 255 for c in rgb):
            raise VolumeEVMError(f"{where}: R G B must be integers in 0..255, got {rgb}")
        yield where, fields[0], fields[7], [c / 255.0 for c in rgb]


def slicer_segments(header, source):
    """The segments a 3D Slicer ``.seg.nrrd`` header describes, checked.

    Parameters
    ----------
    header : dict
        The NRRD header's fields and key/value pairs (as text).
    source : str
        The file, named first in messages.

    Returns
    -------
    list of dict
        One per segment in file order: ``id``, ``name``, ``color`` (RGB in 0..1), ``layer``
        (int) and ``value`` (the label value in that layer).

    Raises
    ------
    VolumeEVMError
        If a segment lacks its name, colour, label value or layer, a number or colour is
        malformed, two segments share a name, or two share a layer and label value.
    """
    numbers = sorted({int(m.group(1)) for key in header
                      if (m := re.fullmatch(r"Segment(\d+)_ID", key))})
    segments, names, places = [], {}, {}
    for n in numbers:
        def field(name):
            key = f"Segment{n}_{name}"
            if key not in header:
                raise VolumeEVMError(f"{source}: segment {n} has no {key}")
            return str(header[key]).strip()

        where = f"{source}: Segment{n}"
        try:
            value, layer = int(field("LabelValue")), int(field("Layer"))
        except ValueError as error:
            raise VolumeEVMError(f"{where}: LabelValue and Layer must be integers "
                                 f"({error})") from error
        if value <= 0 or layer < 0:
            raise VolumeEVMError(f"{where}: LabelValue must be > 0 and Layer >= 0, got {value}, "
                                 f"{layer}")
        try:
            rgb = [float(c) for c in field("Color").split()]
        except ValueError:
            rgb = None
        color = _color(rgb if rgb is not None else field("Color"), f"{where}_Color")
        name = field("Name")
        if name in names:
            raise VolumeEVMError(f"{where}: name {name!r} is also segment {names[name]}'s")
        if (layer, value) in places:
            raise VolumeEVMError(f"{where}: layer {layer}, label value {value} is also segment "
                                 f"{places[layer, value]}'s")
        names[name], places[layer, value] = n, n
        segments.append({"id": field("ID"), "name": name, "color": color, "layer": layer,
                         "value": value})
    return segments


def label_table_for(present, table=None, *, source="volume"):
    """The label table of a map whose labels are ``present``: each present label named and
    coloured by ``table`` where it says, by :func:`default_label_info` otherwise.

    Parameters
    ----------
    present : iterable of int
        The labels in the data (0, the background, is left out).
    table : dict, optional
        ``label -> LabelInfo`` from a file.
    source : str
        Names the data in warnings.

    Returns
    -------
    dict
        ``label -> LabelInfo`` for every present label but 0, in increasing order.

    Warns
    -----
    UserWarning
        Naming the labels the table names but the data lacks, and those the data has but the
        table does not name (they get the palette).
    """
    present = sorted(int(label) for label in present if int(label) != 0)
    table = table or {}
    absent = sorted(set(table) - set(present))
    if absent:
        warnings.warn(f"{source}: the label table names labels the data does not have: {absent}",
                      UserWarning, stacklevel=2)
    unnamed = [label for label in present if label not in table]
    if table and unnamed:
        warnings.warn(f"{source}: labels {unnamed} are not in the label table; they get the "
                      f"default names and colours", UserWarning, stacklevel=2)
    return {label: table.get(label) or default_label_info(label) for label in present}
