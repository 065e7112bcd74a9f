"""The chunked build on a ``dask.distributed`` cluster of 2 worker processes (a
``LocalCluster``): found through Dask's own convention (a ``Client`` exists), identical to the
in-memory build, and the workers read the chunks from the store themselves (the task graph the
client sends holds no voxel data)."""

import pickle

import numpy as np

from skips import required_module
from volumeevm_addon import VolumeEVM, read_volume
from zarr_files import pyramid, write_store

distributed = required_module("distributed")


def test_local_cluster_builds_identically(tmp_path, data_dir):
    ct = np.load(data_dir / "ct_head_invesalius.npy")
    store = write_store(tmp_path / "head.ome.zarr", pyramid(ct, 2), version=3)
    volume = read_volume(store)
    graph = pickle.dumps(dict(volume.array.__dask_graph__()))
    assert len(graph) < ct.nbytes / 100  # metadata and chunk keys, no voxels
    expected = VolumeEVM.from_array(ct, 300, spacing=volume.spacing, source=str(store))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client, distributed.get_task_stream(client) as tasks:
            got = VolumeEVM.from_volume(volume, 300)
    ran = [t for t in tasks.data if "chunk_region" in str(t["key"])]
    assert len(ran) == 4 * 4 * 2, [t["key"] for t in tasks.data][:5]  # every chunk, once
    assert len({t["worker"] for t in ran}) == 2
    assert np.array_equal(got.evm.vertices, expected.evm.vertices)
    for axis in range(3):
        assert got.table(axis).dtype == expected.table(axis).dtype
        assert np.array_equal(got.table(axis), expected.table(axis))
    assert (got.shape, got.spacing, got.origin, got.threshold, got.upper) == (
        expected.shape, expected.spacing, expected.origin, expected.threshold, expected.upper)
