"""OME-Zarr stores for the tests, written chunk by chunk with numcodecs as the Zarr v2 and v3
specifications and OME-NGFF 0.4 / 0.5 lay them out (the zarr library itself cannot be
installed beside numcodecs 0.16 on Python 3.11, see ../shared/design/notes)."""

import json
import math

import numcodecs
import numpy as np

#: Codecs the stores are written with, by name: (v2 compressor config, v3 codec list tail).
CODECS = {
    "blosc": ({"id": "blosc", "cname": "zstd", "clevel": 3, "shuffle": 1, "blocksize": 0},
              [{"name": "blosc", "configuration": {"cname": "zstd", "clevel": 3,
                                                   "shuffle": "shuffle", "typesize": 2,
                                                   "blocksize": 0}}]),
    "zstd": ({"id": "zstd", "level": 3}, [{"name": "zstd", "configuration": {"level": 3}}]),
    "gzip": ({"id": "gzip", "level": 5}, [{"name": "gzip", "configuration": {"level": 5}}]),
    "raw": (None, []),
}


def pyramid(volume_xyz, levels):
    """Level ``k`` = every ``2**k``-th voxel of ``volume_xyz`` (x, y, z), as a z, y, x array."""
    return [np.ascontiguousarray(volume_xyz[::2 ** k, ::2 ** k, ::2 ** k].transpose(2, 1, 0))
            for k in range(levels)]


def write_store(path, arrays, *, version=2, chunks=(64, 64, 64), codec="blosc",
                spacing_zyx=(1.5, 0.957, 0.957), translation_zyx=(0.0, 0.0, 0.0),
                unit="millimeter", axes="zyx", separator=None, fill_value=0, skip=(),
                attributes=None):
    """Write ``arrays`` (level 0 first, store axis order ``axes``) as an OME-Zarr store, with
    the NGFF ``attributes`` (such as ``image-label``) beside ``multiscales``.

    Level ``k`` gets the scale ``spacing * 2**k`` on its spatial axes. ``chunks`` is the
    spatial chunk shape (channel and time chunks are 1). Chunks listed in ``skip`` (level,
    chunk index) are not written (they read as the fill value); chunks equal to the fill value
    are written anyway. Returns the store's path.
    """
    path.mkdir()
    names = list(axes)
    axis_list = [{"name": n, "type": {"t": "time", "c": "channel"}.get(n, "space")}
                 | ({"unit": unit} if n in "zyx" and unit else {}) for n in names]
    datasets = []
    for k, array in enumerate(arrays):
        level_scale = [2.0 ** k * s for s in spacing_zyx]
        scale = [1.0] * (len(names) - 3) + level_scale
        translation = [0.0] * (len(names) - 3) + list(translation_zyx)
        datasets.append({"path": str(k), "coordinateTransformations": [
            {"type": "scale", "scale": scale},
            {"type": "translation", "translation": translation}]})
        _write_array(path / str(k), array, version, (1,) * (len(names) - 3) + tuple(chunks),
                     codec, separator, fill_value, {c for lv, c in skip if lv == k})
    multiscales = [{"version": "0.4" if version == 2 else "0.5", "axes": axis_list,
                    "datasets": datasets}]
    if version == 2:
        (path / ".zgroup").write_text(json.dumps({"zarr_format": 2}))
        (path / ".zattrs").write_text(json.dumps({"multiscales": multiscales,
                                                  **(attributes or {})}))
    else:
        for entry in multiscales:
            del entry["version"]
        (path / "zarr.json").write_text(json.dumps({
            "zarr_format": 3, "node_type": "group",
            "attributes": {"ome": {"version": "0.5", "multiscales": multiscales,
                                   **(attributes or {})}}}))
    return path


def chunk_files(store, level=0):
    """The chunk files of a level, sorted."""
    return sorted(p for p in (store / str(level)).rglob("*")
                  if p.is_file() and not p.name.startswith(".") and p.name != "zarr.json")


def _write_array(folder, array, version, chunks, codec, separator, fill_value, skip):
    folder.mkdir()
    compressor, v3_tail = CODECS[codec]
    grid = [math.ceil(n / c) for n, c in zip(array.shape, chunks)]
    if version == 2:
        separator = separator or "."
        (folder / ".zarray").write_text(json.dumps({
            "zarr_format": 2, "shape": list(array.shape), "chunks": list(chunks),
            "dtype": array.dtype.str, "compressor": compressor, "fill_value": fill_value,
            "order": "C", "filters": None, "dimension_separator": separator}))
        encoder, prefix = (numcodecs.get_codec(dict(compressor)) if compressor else None), ""
    else:
        separator = separator or "/"
        tail = json.loads(json.dumps(v3_tail))
        for entry in tail:
            if entry["name"] == "blosc":
                entry["configuration"]["typesize"] = array.dtype.itemsize
        (folder / "zarr.json").write_text(json.dumps({
            "zarr_format": 3, "node_type": "array", "shape": list(array.shape),
            "data_type": array.dtype.name,
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": list(chunks)}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": separator}},
            "fill_value": fill_value,
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}] + tail}))
        encoder = numcodecs.get_codec(dict(compressor)) if compressor else None
        prefix = "c" + separator
    for index in np.ndindex(*grid):
        if index in skip:
            continue
        block = np.full(chunks, fill_value, array.dtype)
        part = array[tuple(slice(i * c, (i + 1) * c) for i, c in zip(index, chunks))]
        block[tuple(slice(0, n) for n in part.shape)] = part
        data = block.astype(array.dtype.newbyteorder("<")).tobytes()
        if encoder is not None:
            data = bytes(encoder.encode(data))
        target = folder / (prefix + separator.join(str(i) for i in index))
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
