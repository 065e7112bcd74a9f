"""OME-Zarr stores (NGFF 0.4 on Zarr v2, NGFF 0.5 on Zarr v3), read lazily as Dask arrays.

A store is a local folder (``*.zarr``, ``*.ome.zarr``) holding a multiscale pyramid: each level
an N-D array cut into chunk files. :func:`read_zarr` reads only metadata and returns a
:class:`~volumeevm_addon.Volume` whose ``array`` is a Dask array with the store's chunks; a
chunk file is read and decoded when Dask computes that chunk (:class:`ChunkSource`).

Why a reader of our own over numcodecs rather than the zarr library: zarr 3 (the only one that
reads Zarr v3, hence NGFF 0.5) requires NumPy >= 2, which Blender 4.5 does not have, and
zarr 2.18 reads v2 stores only and needs numcodecs < 0.16, the first line with wheels for both
Pythons (``../shared/design/notes/scale_dependencies.md``). The metadata are small JSON
documents and a chunk is one file decoded by a codec chain, so one small reader serves both
store versions on both Blender lines; numcodecs (compiled codecs, wheels for every platform)
does the decoding.

Supported: regular chunk grids, chunk keys ``0.0.0`` or ``0/0/0`` (v2) and the ``default``
and ``v2`` key encodings (v3); v2 compressors and filters that numcodecs knows; the v3 codecs
``bytes``, ``gzip``, ``zstd``, ``blosc`` and ``crc32c``; integer and real floating-point data.
A label image (the group's ``image-label``: a segmentation, as under an image's ``labels/``)
reads as a label map with its ``colors`` (and a ``name`` its ``properties`` give a label).
Sharded v3 arrays and other codecs are refused by name. Axes ``zyx``, ``czyx`` or ``tczyx``
(``channel=`` and ``time=`` pick one 3-D volume); ``scale`` transformations give the spacing
in mm (by the axes' units), ``translation`` the origin; space axes without a unit keep the
scale's numbers as mm with ``spacing_known=False``. Arrays are indexed ``[x, y, z]`` as
every reader's: a transposed view of the store's ``z, y, x``.

Bad input is a :class:`~volumeevm_addon.VolumeEVMError` naming the store (and the level and
chunk where there is one): unreadable or malformed JSON, unsupported axes, units, data types
or codecs, levels whose shapes disagree beyond rounding, a chunk that exists but cannot be
decoded or decodes to the wrong size. A chunk file that does not exist holds the fill value
(the Zarr specification). A chunk's decoded size is checked against memory before decoding.
"""

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from .._memory import check_memory
from ..model._label_table import LabelInfo, default_label_info
from ..model._volume import Volume
from ._checks import MM_PER_UNIT, import_reader_package
from ._labels import label_map

#: NGFF axis names this reader accepts, slowest first.
AXES = (("z", "y", "x"), ("c", "z", "y", "x"), ("t", "c", "z", "y", "x"))

#: The type each NGFF axis name must have when the axis states one.
_AXIS_TYPES = {"t": "time", "c": "channel", "z": "space", "y": "space", "x": "space"}

#: Zarr v3 data types read, as NumPy dtypes (little-endian until the ``bytes`` codec says).
_V3_TYPES = {name: np.dtype(name) for name in ("int8", "int16", "int32", "int64", "uint8",
                                                 "uint16", "uint32", "uint64", "float32",
                                                 "float64")}

#: Length units of NGFF (UDUNITS-2 names) not in the readers' common table, mm per unit.
_NGFF_UNITS = {"angstrom": 1e-7, "picometer": 1e-9, "femtometer": 1e-12, "kilometer": 1e6,
               "decimeter": 100.0, "micrometer": 1e-3}

#: Largest a chunk file may be against its decoded size: compressors add a few header bytes,
#: never more than this; a longer file is not a chunk of this array.
_CHUNK_FILE_SLACK = 1 << 16


@dataclass(frozen=True)
class Level:
    """One level of a store's pyramid: what reading it needs, all checked.

    ``shape`` and ``chunks`` are the stored array's (store axis order); ``spacing`` and
    ``origin`` are x, y, z in mm; ``codecs`` the numcodecs objects that decode a chunk file,
    in decoding order (``None`` for the v3 ``bytes`` codec's byte swap, which is the dtype's).
    """

    store: str
    index: int
    folder: Path
    shape: tuple
    chunks: tuple
    dtype: np.dtype
    fill: object
    order: str
    codecs: tuple
    key_prefix: str
    separator: str
    spacing: tuple
    origin: tuple
    spacing_known: bool

    def where(self, chunk=None):
        """The store, level and chunk, for messages."""
        at = f"{self.store}: level {self.index} ({self.folder.name})"
        return at if chunk is None else f"{at}, chunk {tuple(chunk)}"

    @property
    def xyz_shape(self):
        """The 3-D grid ``(X, Y, Z)`` of one channel and time point."""
        return tuple(reversed(self.shape[-3:]))

    @property
    def chunk_bytes(self):
        """Bytes of one decoded chunk."""
        return math.prod(self.chunks) * self.dtype.itemsize


class ChunkSource:
    """The level's array as Dask reads it: ``source[slices]`` for chunk-aligned slices decodes
    that chunk file (``dask.array.from_array`` with ``fancy=False``). Small and picklable, so
    a distributed cluster's workers read the chunks themselves."""

    def __init__(self, level):
        self.level = level
        self.shape = level.shape
        self.dtype = level.dtype.newbyteorder("=")
        self.ndim = len(level.shape)

    def __getitem__(self, slices):
        level = self.level
        chunk = tuple(s.start // c for s, c in zip(slices, level.chunks))
        data = read_chunk(level, chunk)
        return data[tuple(slice(s.start - i * c, s.stop - i * c)
                          for s, i, c in zip(slices, chunk, level.chunks))]


def read_chunk(level, chunk):
    """The decoded chunk ``chunk`` (its grid index) of ``level``, full chunk shape, native byte
    order; the fill value when its file does not exist.

    Raises
    ------
    VolumeEVMError
        If the file exists but cannot be read or decoded, or decodes to another size, naming
        the store, level and chunk.
    """
    key = level.key_prefix + level.separator.join(str(i) for i in chunk)
    path = level.folder / key
    native = level.dtype.newbyteorder("=")
    try:
        size = os.stat(path).st_size
    except FileNotFoundError:
        return np.full(level.chunks, level.fill, native)
    except OSError as exc:
        raise VolumeEVMError(f"{level.where(chunk)}: cannot read {key} ({exc.strerror})") from exc
    if size > level.chunk_bytes + _CHUNK_FILE_SLACK:
        raise VolumeEVMError(f"{level.where(chunk)}: {key} holds {size} bytes, more than a chunk "
                             f"of {level.chunk_bytes} bytes can be encoded in")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise VolumeEVMError(f"{level.where(chunk)}: cannot read {key} ({exc.strerror})") from exc
    for codec in level.codecs:
        try:
            data = codec.decode(data)
        except Exception as exc:  # noqa: BLE001 - a codec fails in its own ways on bad bytes
            raise VolumeEVMError(
                f"{level.where(chunk)}: {key} cannot be decoded by {codec.codec_id} "
                f"({type(exc).__name__}: {exc})") from exc
    data = memoryview(np.ascontiguousarray(data)).cast("B")
    if data.nbytes != level.chunk_bytes:
        raise VolumeEVMError(f"{level.where(chunk)}: {key} decodes to {data.nbytes} bytes, but a "
                             f"chunk of {level.chunks} {level.dtype.name} has {level.chunk_bytes}")
    array = np.frombuffer(data, level.dtype).reshape(level.chunks, order=level.order)
    return array.astype(native, order="C")


def read_zarr(path, level=0, channel=0, time=0, *, label_image=True):
    """Open one level of an OME-Zarr store lazily: metadata now, chunks when computed.

    Parameters
    ----------
    path : str or Path
        The store's folder.
    level : int
        The pyramid level (0 = full resolution).
    channel, time : int
        The channel and time point, for stores with those axes.
    label_image : bool
        Whether a label image (NGFF ``image-label``) reads as a label map (False: its values,
        without the pass that finds its labels).

    Returns
    -------
    Volume
        ``array`` a Dask array ``(X, Y, Z)`` with the store's chunks; spacing and origin from
        the level's coordinate transformations, in mm. A label image (NGFF ``image-label``) is
        a label map with the store's colours: its labels are found chunk by chunk, a pass over
        the level.

    Raises
    ------
    VolumeEVMError
        For a store, level, channel or time that is not as described (see the module).
    """
    levels, axes, attrs = _levels(Path(path))
    chosen = _choice(level, "level", len(levels), path)
    selection = []
    for name, value in (("t", time), ("c", channel)):
        option = {"t": "time", "c": "channel"}[name]
        if name in axes:
            selection.append(_choice(value, option, levels[0].shape[axes.index(name)], path))
        elif value != 0:
            raise VolumeEVMError(f"{path}: {option}={value!r}, but the store's axes "
                                 f"{''.join(axes)} have no {option} axis")
    chosen = levels[chosen]
    da = import_reader_package("dask.array", "dask", path)
    import dask.base

    check_memory(2 * chosen.chunk_bytes, "decoding one chunk", source=chosen.where(),
                 advice="rewrite the store with smaller chunks")
    name = "ome-zarr-" + dask.base.tokenize(
        str(chosen.folder.resolve()), chosen.shape, chosen.chunks, chosen.dtype.str,
        chosen.order, repr(chosen.fill), [repr(c.get_config()) for c in chosen.codecs])
    array = da.from_array(ChunkSource(chosen), chunks=chosen.chunks, name=name, asarray=False,
                          fancy=False, meta=np.empty((0,) * len(chosen.shape), chosen.dtype))
    array = array[tuple(selection)].transpose(2, 1, 0)
    volume = Volume(array=array, spacing=chosen.spacing, origin=chosen.origin, source=str(path),
                    spacing_known=chosen.spacing_known)
    table = _image_label(attrs, path) if label_image else None
    return volume if table is None else label_map(volume, table)


def volume_levels(path):
    """The levels of an OME-Zarr store's pyramid, from its metadata alone.

    Parameters
    ----------
    path : str or Path
        The store's folder (``*.zarr``, ``*.ome.zarr``).

    Returns
    -------
    list of dict
        One per level, finest first: ``level`` (its index, as ``read_volume(level=)`` takes),
        ``path`` (its folder in the store), ``shape`` (``(X, Y, Z)``), ``chunks`` (``(X, Y,
        Z)``), ``dtype``, ``spacing`` (mm, x, y, z), ``spacing_known`` and ``bytes`` (of one
        channel and time point, decoded).

    Raises
    ------
    VolumeEVMError
        If the store's metadata are unreadable or not a supported OME-Zarr pyramid.

    Examples
    --------
    >>> [(lv["level"], lv["shape"]) for lv in volume_levels("head.ome.zarr")]  # doctest: +SKIP
    [(0, (256, 256, 108)), (1, (128, 128, 54)), (2, (64, 64, 27))]
    """
    levels, _, _ = _levels(Path(path))
    return [{"level": lv.index, "path": lv.folder.name, "shape": lv.xyz_shape,
             "chunks": tuple(reversed(lv.chunks[-3:])), "dtype": lv.dtype.newbyteorder("=").name,
             "spacing": lv.spacing, "spacing_known": lv.spacing_known,
             "bytes": math.prod(lv.xyz_shape) * lv.dtype.itemsize} for lv in levels]


def _choice(value, name, count, store):
    """``value`` checked as an index below ``count``."""
    integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if not integer or not 0 <= value < count:
        raise VolumeEVMError(f"{store}: {name}={value!r} is not one of 0 .. {count - 1}")
    return int(value)


def _json(path, store):
    """The JSON object in ``path``; ``None`` when the file does not exist."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise VolumeEVMError(f"{store}: cannot read {path.name} ({exc})") from exc
    try:
        value = json.loads(text)
    except ValueError as exc:
        raise VolumeEVMError(
            f"{store}: {path.relative_to(store)} is not valid JSON ({exc})") from exc
    if not isinstance(value, dict):
        raise VolumeEVMError(f"{store}: {path.relative_to(store)} is not a JSON object")
    return value


def _group(store):
    """The store group's OME-NGFF attributes (v3: ``attributes.ome``; v2: ``.zattrs``) and the
    Zarr version."""
    if not store.is_dir():
        raise VolumeEVMError(f"{store}: an OME-Zarr store is a folder; this is not one")
    group = _json(store / "zarr.json", store)
    if group is not None:
        if group.get("zarr_format") != 3 or group.get("node_type") != "group":
            raise VolumeEVMError(f"{store}: zarr.json is not a Zarr v3 group")
        ome = (group.get("attributes") or {}).get("ome")
        return (ome if isinstance(ome, dict) else {}), 3
    attrs = _json(store / ".zattrs", store)
    if attrs is None:
        raise VolumeEVMError(f"{store}: neither zarr.json (Zarr v3) nor .zattrs (Zarr v2): "
                             f"not an OME-Zarr store")
    return attrs, 2


def _image_label(attrs, store):
    """An ``image-label`` store's label table, ``label -> LabelInfo``, from its ``colors``
    (``label-value``, ``rgba`` in 0..255; alpha left out) and the string ``name`` its
    ``properties`` may give a label; ``None`` for a store that is not a label image."""
    meta = attrs.get("image-label")
    if meta is None:
        return None
    where = f"{store}: image-label"
    if not isinstance(meta, dict):
        raise VolumeEVMError(f"{where} is not a JSON object")
    names = {}
    for entry in meta.get("properties") or []:
        if isinstance(entry, dict) and isinstance(entry.get("name"), str):
            names[_label_value(entry, where)] = entry["name"]
    table = {}
    colors = meta.get("colors") or []
    if not isinstance(colors, list):
        raise VolumeEVMError(f"{where} colors is not a list")
    for index, entry in enumerate(colors):
        if not isinstance(entry, dict):
            raise VolumeEVMError(f"{where} colors[{index}] is not an object")
        label = _label_value(entry, f"{where} colors[{index}]")
        rgba = entry.get("rgba")
        if (not isinstance(rgba, list) or len(rgba) != 4
                or not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255
                           for c in rgba)):
            raise VolumeEVMError(f"{where} colors[{index}]: rgba must be 4 integers in 0..255, "
                                 f"got {rgba!r}")
        if label in table:
            raise VolumeEVMError(f"{where} colors: label-value {label} is given twice")
        table[label] = LabelInfo(names.get(label, default_label_info(label).name),
                                 tuple(round(c / 255, 6) for c in rgba[:3]))
    return table


def _label_value(entry, where):
    """An entry's ``label-value``: an integer >= 0."""
    value = entry.get("label-value")
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise VolumeEVMError(f"{where}: label-value must be an integer >= 0, got {value!r}")
    return value


def _levels(store):
    """The store's checked levels, its axis names and its group's NGFF attributes
    (:func:`_group`)."""
    attrs, version = _group(store)
    multiscales = attrs.get("multiscales")
    if not isinstance(multiscales, list) or not multiscales or not isinstance(multiscales[0], dict):
        raise VolumeEVMError(f"{store}: no OME-NGFF 'multiscales' in the group's attributes")
    scales = multiscales[0]
    axes, units = _axes(scales.get("axes"), store)
    datasets = scales.get("datasets")
    if not isinstance(datasets, list) or not datasets:
        raise VolumeEVMError(f"{store}: multiscales has no datasets (levels)")
    outer = _transforms(scales.get("coordinateTransformations", []), len(axes), store,
                        "multiscales")
    levels = []
    for index, dataset in enumerate(datasets):
        if not isinstance(dataset, dict) or not isinstance(dataset.get("path"), str):
            raise VolumeEVMError(f"{store}: dataset {index} has no path")
        folder = store / dataset["path"]
        where = f"level {index} ({dataset['path']})"
        if not folder.resolve().is_relative_to(store.resolve()):
            raise VolumeEVMError(f"{store}: {where} lies outside the store")
        scale, shift = _transforms(dataset.get("coordinateTransformations"), len(axes), store,
                                   where, required=True)
        scale, shift = scale * outer[0], shift * outer[0] + outer[1]
        array = (_array_v3 if version == 3 else _array_v2)(folder, store, where)
        if len(array["shape"]) != len(axes):
            raise VolumeEVMError(f"{store}: {where} has {len(array['shape'])} dimensions but the "
                                 f"axes are {''.join(axes)}")
        mm = np.array([units[axes.index(a)] or 1.0 for a in "xyz"])
        spacing = tuple(float(s) for s in scale[[axes.index(a) for a in "xyz"]] * mm)
        origin = tuple(float(s) for s in shift[[axes.index(a) for a in "xyz"]] * mm)
        levels.append(Level(store=str(store), index=index, folder=folder, spacing=spacing,
                            origin=origin, spacing_known=all(units[-3:]), **array))
    _check_pyramid(levels, store)
    return levels, axes, attrs


def _axes(axes, store):
    """Axis names (one of :data:`AXES`) and mm per unit of each (``None``: no unit)."""
    if not isinstance(axes, list) or not all(isinstance(a, (dict, str)) for a in axes):
        raise VolumeEVMError(f"{store}: multiscales 'axes' is not a list of axes")
    axes = [a if isinstance(a, dict) else {"name": a} for a in axes]
    names = tuple(str(a.get("name")) for a in axes)
    if names not in AXES:
        raise VolumeEVMError(f"{store}: axes {', '.join(names)} are not supported; VolumeEVM reads "
                             f"{', '.join(''.join(a) for a in AXES)}")
    units = []
    for axis in axes:
        name, kind, unit = axis["name"], axis.get("type"), axis.get("unit")
        if kind is not None and kind != _AXIS_TYPES[name]:
            raise VolumeEVMError(f"{store}: axis {name} has type {kind!r}, expected "
                                 f"{_AXIS_TYPES[name]!r}")
        if _AXIS_TYPES[name] != "space" or unit is None:
            units.append(None)
            continue
        key = str(unit).strip().lower()
        table = {**MM_PER_UNIT, **_NGFF_UNITS}
        if key not in table:
            raise VolumeEVMError(f"{store}: axis {name} has unit {unit!r}, not a length unit "
                                 f"VolumeEVM knows ({', '.join(sorted(table))})")
        units.append(table[key])
    return names, units


def _transforms(transforms, ndim, store, where, required=False):
    """``(scale, translation)`` arrays from NGFF coordinate transformations."""
    scale, shift = np.ones(ndim), np.zeros(ndim)
    if not isinstance(transforms, list) or (required and not transforms):
        raise VolumeEVMError(f"{store}: {where} has no coordinateTransformations list")
    for item in transforms:
        kind = item.get("type") if isinstance(item, dict) else None
        if kind not in ("scale", "translation", "identity"):
            raise VolumeEVMError(f"{store}: {where}: coordinate transformation {item!r} is not "
                                 f"scale, translation or identity")
        if kind == "identity":
            continue
        values = item.get(kind)
        if (not isinstance(values, list) or len(values) != ndim
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
                or not all(math.isfinite(v) for v in values)):
            raise VolumeEVMError(
                f"{store}: {where}: {kind} {values!r} is not {ndim} finite numbers")
        if kind == "scale":
            if min(values) <= 0:
                raise VolumeEVMError(f"{store}: {where}: scale {values} must be positive")
            scale = scale * values
        else:
            shift = shift + values
    return scale, shift


def _shape(value, name, where, store):
    """A list of positive ints, or refused."""
    if (not isinstance(value, list) or not value
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)):
        raise VolumeEVMError(f"{store}: {where}: {name} {value!r} is not a list of positive "
                             f"integers")
    if name == "shape" and max(value) >= 1 << 20:
        raise VolumeEVMError(f"{store}: {where}: shape {value} exceeds the {(1 << 20) - 1} voxels "
                             f"per axis a VolumeEVM holds")
    return tuple(value)


def _dtype(dtype, where, store):
    """A NumPy dtype of integers or real floating-point numbers."""
    try:
        dtype = np.dtype(dtype)
    except (TypeError, ValueError) as exc:
        raise VolumeEVMError(f"{store}: {where}: data type {dtype!r} is not readable") from exc
    if dtype.kind not in "iuf" or dtype.itemsize > 8 or dtype.fields is not None:
        raise VolumeEVMError(f"{store}: {where}: data type {dtype} is not integers or real "
                             f"floating-point numbers")
    return dtype


def _fill(value, dtype, where, store):
    """The fill value as a scalar of ``dtype`` (0 for ``null``)."""
    special = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}
    value = 0 if value is None else special.get(value, value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise VolumeEVMError(f"{store}: {where}: fill value {value!r} is not a number")
    if dtype.kind in "iu" and (not float(value).is_integer()
                               or not np.iinfo(dtype).min <= value <= np.iinfo(dtype).max):
        raise VolumeEVMError(f"{store}: {where}: fill value {value!r} is not a {dtype.name}")
    return value


def _codec(numcodecs, config, where, store):
    """The numcodecs codec a configuration names, or refused naming it."""
    name = config.get("id") if isinstance(config, dict) else config
    try:
        return numcodecs.get_codec(dict(config))
    except Exception as exc:  # noqa: BLE001 - unknown ids and bad parameters raise several types
        raise VolumeEVMError(f"{store}: {where}: codec {name!r} is not installed or "
                             f"not usable ({exc})") from exc


def _array_v2(folder, store, where):
    """The checked ``.zarray`` of a Zarr v2 level."""
    meta = _json(folder / ".zarray", store)
    if meta is None or meta.get("zarr_format") != 2:
        raise VolumeEVMError(f"{store}: {where} has no Zarr v2 array (.zarray)")
    numcodecs = import_reader_package("numcodecs", "numcodecs", store)
    filters = meta.get("filters") or []
    if not isinstance(filters, list):
        raise VolumeEVMError(f"{store}: {where}: filters {filters!r} is not a list")
    compressor = meta.get("compressor")
    codecs = [] if compressor is None else [_codec(numcodecs, compressor, where, store)]
    codecs += [_codec(numcodecs, f, where, store) for f in reversed(filters)]
    dtype = _dtype(meta.get("dtype"), where, store)
    if meta.get("order", "C") not in ("C", "F"):
        raise VolumeEVMError(f"{store}: {where}: order {meta.get('order')!r} is not C or F")
    separator = meta.get("dimension_separator", ".")
    if separator not in (".", "/"):
        raise VolumeEVMError(f"{store}: {where}: dimension_separator {separator!r} is not . or /")
    shape = _shape(meta.get("shape"), "shape", where, store)
    chunks = _shape(meta.get("chunks"), "chunks", where, store)
    return {"shape": shape, "chunks": _same_rank(chunks, shape, where, store), "dtype": dtype,
            "fill": _fill(meta.get("fill_value"), dtype, where, store),
            "order": meta.get("order", "C"), "codecs": tuple(codecs), "key_prefix": "",
            "separator": separator}


def _array_v3(folder, store, where):
    """The checked ``zarr.json`` of a Zarr v3 level."""
    meta = _json(folder / "zarr.json", store)
    if meta is None or meta.get("zarr_format") != 3 or meta.get("node_type") != "array":
        raise VolumeEVMError(f"{store}: {where} has no Zarr v3 array (zarr.json)")
    numcodecs = import_reader_package("numcodecs", "numcodecs", store)
    if meta.get("data_type") not in _V3_TYPES:
        raise VolumeEVMError(f"{store}: {where}: data type {meta.get('data_type')!r} is not one "
                             f"of {', '.join(_V3_TYPES)}")
    dtype = _V3_TYPES[meta["data_type"]].newbyteorder("<")
    grid = meta.get("chunk_grid")
    if not isinstance(grid, dict) or grid.get("name") != "regular":
        raise VolumeEVMError(f"{store}: {where}: chunk grid {grid!r} is not a regular grid")
    chunks = _shape((grid.get("configuration") or {}).get("chunk_shape"), "chunk_shape", where,
                    store)
    encoding = meta.get("chunk_key_encoding", {"name": "default"})
    name = encoding.get("name") if isinstance(encoding, dict) else None
    if name not in ("default", "v2"):
        raise VolumeEVMError(f"{store}: {where}: chunk key encoding {encoding!r} is not "
                             f"supported")
    separator = (encoding.get("configuration") or {}).get(
        "separator", "/" if name == "default" else ".")
    if separator not in (".", "/"):
        raise VolumeEVMError(f"{store}: {where}: chunk key separator {separator!r} is not . or /")
    codecs = meta.get("codecs")
    if not isinstance(codecs, list) or not codecs:
        raise VolumeEVMError(f"{store}: {where}: no codecs list")
    decoders = []
    seen_bytes = False
    for config in codecs:
        cname = config.get("name") if isinstance(config, dict) else None
        options = (config.get("configuration") or {}) if cname else {}
        if cname == "bytes" and not seen_bytes:
            seen_bytes = True
            endian = options.get("endian", "little")
            if endian not in ("little", "big"):
                raise VolumeEVMError(f"{store}: {where}: bytes codec endian {endian!r}")
            dtype = dtype.newbyteorder("<" if endian == "little" else ">")
        elif cname in ("gzip", "zstd", "blosc", "crc32c") and seen_bytes:
            decoders.insert(0, _codec(numcodecs, _v3_codec(cname, options), where, store))
        else:
            raise VolumeEVMError(f"{store}: {where}: codec {cname or config!r} is not supported "
                                 f"here (supported: bytes, then gzip, zstd, blosc, crc32c; no "
                                 f"sharding or transpose)")
    if not seen_bytes:
        raise VolumeEVMError(f"{store}: {where}: no bytes codec")
    shape = _shape(meta.get("shape"), "shape", where, store)
    return {"shape": shape, "chunks": _same_rank(chunks, shape, where, store), "dtype": dtype,
            "fill": _fill(meta.get("fill_value"), dtype, where, store), "order": "C",
            "codecs": tuple(decoders), "key_prefix": "c" + separator if name == "default" else "",
            "separator": separator}


def _v3_codec(name, options):
    """The numcodecs configuration of a Zarr v3 bytes-to-bytes codec."""
    if name == "blosc":
        shuffle = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}.get(options.get("shuffle"), 1)
        return {"id": "blosc", "cname": options.get("cname", "lz4"),
                "clevel": options.get("clevel", 5), "shuffle": shuffle,
                "blocksize": options.get("blocksize", 0)}
    if name == "crc32c":
        return {"id": "crc32c"}
    return {"id": name, "level": options.get("level", 1)}


def _same_rank(chunks, shape, where, store):
    """``chunks`` refused unless it has one entry per dimension of ``shape``."""
    if len(chunks) != len(shape):
        raise VolumeEVMError(f"{store}: {where}: chunks {list(chunks)} do not match shape "
                             f"{list(shape)}")
    return chunks


def _check_pyramid(levels, store):
    """Refuse levels whose physical extent or non-spatial axes disagree with level 0's."""
    first = levels[0]
    extent = np.array(first.xyz_shape) * first.spacing
    for level in levels[1:]:
        if level.shape[:-3] != first.shape[:-3]:
            raise VolumeEVMError(f"{level.where()}: channel/time sizes {level.shape[:-3]} differ "
                                 f"from level 0's {first.shape[:-3]}")
        size = np.array(level.xyz_shape) * level.spacing
        if np.any(np.abs(size - extent) > np.array(level.spacing) + 1e-9 * extent):
            raise VolumeEVMError(
                f"{level.where()}: shape {level.xyz_shape} with spacing {level.spacing} covers "
                f"{size.tolist()} mm but level 0 covers {extent.tolist()} mm (more than one "
                f"voxel of rounding apart)")
