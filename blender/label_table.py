"""A label map's label table on its volume object, and the categorical transfer function the
renderers take from it.

Importing a label map (a 3D Slicer ``.seg.nrrd``, or any integer volume read with
``labels=True``) stores one row per label in ``Object.volumeevm.labels`` (saved in the .blend):
its value, name and colour from the file (the core's palette where the file names none), an
opacity and whether it is shown. While the object's ``use_label_colors`` is on (the default)
Render VolumeEVM, F12's DVR image and the Viewport DVR render the label map with
:meth:`TransferFunction.categorical` of that table (:func:`label_transfer_function`): each
sample takes its nearest voxel's label, every label its colour, hidden labels and the
background (0) transparent. Editing a row (the Render panel's list, or :func:`set_label`)
redraws the viewports; the next render reads the table again.
"""

from ..volumeevm_addon import TransferFunction, VolumeEVMError
from .objects import volume_object

#: Opacity per Opacity Length (the Render settings' ``unit_length_mm``) a label starts with.
DEFAULT_OPACITY = 0.5


def store_labels(vol_obj, infos):
    """Fill ``vol_obj``'s label table from ``infos`` (label -> :class:`LabelInfo`, as in
    ``Volume.labels``), in increasing label order, each shown at :data:`DEFAULT_OPACITY`."""
    table = vol_obj.volumeevm.labels
    table.clear()
    for label in sorted(infos):
        row = table.add()
        row.label, row.name, row.color = int(label), infos[label].name, infos[label].color
        row.opacity, row.show = DEFAULT_OPACITY, True


def uses_labels(vol_obj):
    """Whether ``vol_obj`` (a volume object, or None) is rendered with its label table."""
    return (vol_obj is not None and vol_obj.volumeevm.use_label_colors
            and len(vol_obj.volumeevm.labels) > 0)


def label_transfer_function(obj, *, unit_length_mm=1.0):
    """The categorical transfer function of a label map's label table.

    Parameters
    ----------
    obj : bpy.types.Object
        A label map's volume object (or its surface).
    unit_length_mm : float, optional
        The length in mm over which a label's opacity accumulates (default 1 mm; the renders
        use the Render settings' Opacity Length).

    Returns
    -------
    TransferFunction
        ``is_categorical``: each label its colour and opacity, hidden labels and values
        without a label (the background) transparent.

    Raises
    ------
    VolumeEVMError
        ``obj`` is not a volume object, or its volume has no label table (not a label map).
    """
    vol_obj = volume_object(obj)
    table = vol_obj.volumeevm.labels
    if not len(table):
        raise VolumeEVMError(f"{vol_obj.name}: not a label map (no label table)")
    colours = {row.label: (*row.color, row.opacity if row.show else 0.0) for row in table}
    return TransferFunction.categorical(colours, unit_length_mm=unit_length_mm,
                                        name=f"{vol_obj.name} labels")


def _row(vol_obj, label):
    for row in vol_obj.volumeevm.labels:
        if row.label == label:
            return row
    raise VolumeEVMError(f"label: {vol_obj.name} has no label {label!r} (its labels: "
                         f"{[row.label for row in vol_obj.volumeevm.labels]})")


def set_label(obj, label, *, color=None, opacity=None, visible=None):
    """Change how one label of a label map is rendered; the viewports redraw and the next
    render shows it.

    Parameters
    ----------
    obj : bpy.types.Object
        A label map's volume object (or its surface).
    label : int
        The label's value in the label map.
    color : tuple of float, optional
        Straight ``(r, g, b)`` in ``[0, 1]``.
    opacity : float, optional
        In ``[0, 1]``, per the Render settings' Opacity Length.
    visible : bool, optional
        False hides the label (transparent), True shows it again.

    Returns
    -------
    dict
        The label's row afterwards: ``name``, ``color``, ``opacity``, ``visible``.

    Raises
    ------
    VolumeEVMError
        Not a volume object, a label the map does not have, a colour that is not three
        numbers in ``[0, 1]`` or an opacity outside ``[0, 1]`` (nothing is changed then).
    """
    row = _row(volume_object(obj), label)
    if color is not None:
        try:
            color = tuple(float(c) for c in color)
        except (TypeError, ValueError):
            raise VolumeEVMError(f"color: expected (r, g, b), got {color!r}") from None
        if len(color) != 3 or not all(0.0 <= c <= 1.0 for c in color):
            raise VolumeEVMError(f"color: expected (r, g, b) in [0, 1], got {color!r}")
    if opacity is not None and not 0.0 <= float(opacity) <= 1.0:
        raise VolumeEVMError(f"opacity: expected a number in [0, 1], got {opacity!r}")
    if color is not None:
        row.color = color
    if opacity is not None:
        row.opacity = float(opacity)
    if visible is not None:
        row.show = bool(visible)
    return get_label(obj, label)


def get_label(obj, label):
    """One label's row of a label map's table as a dict (``name``, ``color``, ``opacity``,
    ``visible``); see :func:`set_label`.

    Raises
    ------
    VolumeEVMError
        Not a volume object, or a label the map does not have.
    """
    row = _row(volume_object(obj), label)
    return {"name": row.name, "color": tuple(row.color), "opacity": row.opacity,
            "visible": row.show}

