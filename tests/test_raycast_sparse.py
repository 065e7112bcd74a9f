"""Ray casting's block-sparse sampling table (issue 18): the same samples as the dense table it
replaced, bit for bit, in memory that follows the region.

The dense way is kept here as the reference: the padded complex64 grid ``density·r + i·r``
made from the region mask (what ``_raycast._dense_table`` built) and its gradients from
:func:`region_gradients` over the whole padded grid. It is compared with the sparse table
block by block (the sparse table stores NaN where the dense one had ``r = 0``), and rendered:
the dense grid cut into blocks with every block stored, put in the VolumeEVM's cache in place
of the sparse table, gives the image the old table gave."""

import json

import numpy as np
import pytest

from render_helpers import camera
from volumeevm_addon import EVM, TransferFunction, VolumeEVM, grid_to_world
from volumeevm_addon.rendering import _raycast
from volumeevm_addon.rendering._gradients import region_gradients
from volumeevm_addon.rendering._ray_march import BLOCK_VOXELS, TABLE_BLOCK
from volumeevm_addon.rendering._raycast import _SamplingTable, render_raycast

EDGE = TABLE_BLOCK + 1


def dense_table(vevm):
    """The padded dense table the ray caster sampled before (complex64 ``density·r + i·r``)."""
    mask = vevm.evm.to_mask(vevm.shape)
    tab = np.zeros(tuple(int(n) + 2 for n in vevm.shape), np.complex64)
    tab[1:-1, 1:-1, 1:-1].real[mask] = vevm.table(0)
    tab[1:-1, 1:-1, 1:-1].imag[...] = mask
    return tab


def dense_gradients(tab):
    """The gradients the ray caster read before: :func:`region_gradients` over the whole
    padded dense table, (X + 2, Y + 2, Z + 2, 3) float32."""
    grad = np.zeros(tab.shape + (3,), np.float32)
    region_gradients(tab.real, tab.imag, np.moveaxis(grad, -1, 0)[:, 1:-1, 1:-1, 1:-1])
    return grad


def blocks_of(grid, shape):
    """``grid`` (padded, trailing channels allowed) cut into the blocks of the sparse table's
    block grid ``shape``, each with its apron: (blocks, EDGE, EDGE, EDGE, ...)."""
    size = [s * TABLE_BLOCK + 1 for s in shape]
    big = np.zeros(tuple(size) + grid.shape[3:], grid.dtype)
    big[:grid.shape[0], :grid.shape[1], :grid.shape[2]] = grid
    return np.stack([big[x * TABLE_BLOCK:x * TABLE_BLOCK + EDGE,
                         y * TABLE_BLOCK:y * TABLE_BLOCK + EDGE,
                         z * TABLE_BLOCK:z * TABLE_BLOCK + EDGE]
                     for x, y, z in np.ndindex(*shape)])


class DenseAsBlocks:
    """The dense table in the sparse table's layout with every block stored: the old table,
    read through the block index."""

    def __init__(self, vevm):
        self.tab = dense_table(vevm)
        self.shape = tuple(int(n) // TABLE_BLOCK + 1 for n in vevm.shape)
        self.strides = (self.shape[1] * self.shape[2], self.shape[2], 1)
        self.index = np.arange(np.prod(self.shape), dtype=np.int32)
        self.table = blocks_of(nan_outside(self.tab), self.shape).ravel()
        self.hole = np.float32(np.nan)

    def gradients(self):
        return blocks_of(dense_gradients(self.tab), self.shape).ravel()


def nan_outside(tab):
    """The dense complex64 table as the sparse table stores voxels: the density, NaN outside
    the region."""
    return np.where(tab.imag > 0, tab.real, np.float32(np.nan)).astype(np.float32)


def bits(a):
    """The bit patterns of a float32 array (so -0.0 and 0.0 differ, and NaN equals itself)."""
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def real_volumes(data_dir):
    """VolumeEVMs of real volumes: the CT head (bone, and skin: a large region), brainsmall and
    the T1 MRI's k-means labels (categorical)."""
    def load(name, step=(1, 1, 1)):
        meta = json.loads((data_dir / f"{name}.json").read_text())
        a = np.load(data_dir / f"{name}.npy")[::step[0], ::step[1], ::step[2]]
        return a, tuple(np.array(meta["spacing_mm"]) * step)

    ct, ct_sp = load("ct_head_invesalius", (2, 2, 2))
    brain, brain_sp = load("mr_brainsmall_volpack", (2, 2, 2))
    labels, labels_sp = load("mr_t1_itk_kmeans", (2, 2, 2))
    return {"ct_bone": VolumeEVM.from_array(ct, 300, spacing=ct_sp),
            "ct_skin": VolumeEVM.from_array(ct, -300, spacing=ct_sp),
            "brain": VolumeEVM.from_array(brain, 60, spacing=brain_sp),
            "labels": VolumeEVM.from_array(labels, 1, upper=int(labels.max()),
                                           spacing=labels_sp)}


@pytest.fixture(scope="module")
def volumes(data_dir):
    return real_volumes(data_dir)


@pytest.mark.parametrize("name", ["ct_bone", "ct_skin", "brain", "labels"])
def test_sparse_table_holds_the_dense_table_block_by_block(volumes, name):
    """Every stored block (with its apron) equals the dense table's voxels there, bit for bit,
    densities, region flags and gradients; every block left out is zero in the dense table
    (its samples read zeros, as they did)."""
    vevm = volumes[name]
    sparse = _SamplingTable(vevm)
    tab = dense_table(vevm)
    index = sparse.index.reshape(sparse.shape)
    stored = index >= 0
    assert np.array_equal(index[stored], np.arange(stored.sum()))  # pool order: C order
    dense = blocks_of(tab, sparse.shape).reshape(sparse.shape + (EDGE,) * 3)
    pool = sparse.table.reshape((-1,) + (EDGE,) * 3)
    # 16-bit densities stay in their type, the type's smallest value outside the region.
    pool = np.where(pool == sparse.hole, np.float32(np.nan), pool.astype(np.float32))
    assert np.array_equal(bits(pool), bits(nan_outside(dense[stored])))
    assert not dense[~stored].any()
    assert stored.sum() < stored.size  # something is left out
    grad = blocks_of(dense_gradients(tab), sparse.shape).reshape(sparse.shape + (EDGE,) * 3 + (3,))
    assert np.array_equal(bits(sparse.gradients()), bits(grad[stored].ravel()))
    assert not grad[~stored].any()


CASES = [{}, {"shading": True}, {"mode": "under"}, {"mode": "mip"},
         {"mode": "xray", "xray_scale": 2e-4}, {"jitter": True, "preintegrate": True},
         {"skip_empty": False, "shading": True}]


@pytest.mark.parametrize("name", ["ct_bone", "ct_skin", "brain"])
@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_sparse_renders_equal_dense_renders_bit_for_bit(volumes, name, kind):
    """Every mode and option, both cameras: the image and depth of the sparse table equal those
    of the dense table (every block stored) bit for bit."""
    vevm = volumes[name]
    g = grid_to_world(vevm.spacing, vevm.origin)
    tf = TransferFunction.preset("mri" if name == "brain" else name, data_range=(0, 202))
    cam = camera(kind, g, vevm, (0.25, -0.4, 0.2), 0.3, res=(40, 32))
    old = VolumeEVM(vevm.evm, vevm.table(), shape=vevm.shape, spacing=vevm.spacing)
    dense = DenseAsBlocks(old)
    old.cache.get(("raycast", "table"), lambda: dense)
    old.cache.get(("raycast", "gradients"), dense.gradients)
    for options in CASES:
        new_rgba, new_depth = render_raycast(vevm, cam, tf, g, **options)
        old_rgba, old_depth = render_raycast(old, cam, tf, g, **options)
        assert old.cache.get(("raycast", "table"), lambda: None) is dense  # the dense one ran
        assert new_rgba[..., 3].max() > 0.1, options
        assert np.array_equal(bits(new_rgba), bits(old_rgba)), options
        assert np.array_equal(bits(new_depth), bits(old_depth)), options


def test_categorical_sparse_render_equals_dense_render(volumes):
    """Labels (nearest voxel, never interpolated) through the sparse table: the dense image."""
    vevm = volumes["labels"]
    g = grid_to_world(vevm.spacing, vevm.origin)
    labels = np.unique(vevm.table())
    tf = TransferFunction.categorical({int(v): (0.2 + 0.8 * (i % 2), 0.5, 1.0 - 0.3 * (i % 3))
                                       for i, v in enumerate(labels)}, opacity=0.3)
    cam = camera("PERSP", g, vevm, (0.3, 0.35, 0.15), 0.0, res=(40, 32))
    old = VolumeEVM(vevm.evm, vevm.table(), shape=vevm.shape, spacing=vevm.spacing)
    old.cache.get(("raycast", "table"), lambda: DenseAsBlocks(old))
    new, old_image = render_raycast(vevm, cam, tf, g), render_raycast(old, cam, tf, g)
    assert new[0][..., 3].max() > 0.1
    for a, b in zip(new, old_image):
        assert np.array_equal(bits(a), bits(b))



def test_table_memory_follows_the_region():
    """A small sphere in a big grid: the table stores the blocks around the sphere alone,
    a small fraction of the dense table's bytes; the cache holds that much (and the block
    index), and the memory check's estimate covers it without the dense grid's size."""
    n, r = 160, 6
    x, y, z = np.indices((n, n, n), dtype=np.float32) - np.float32(n / 3)
    dens = np.float32(r) - np.sqrt(x * x + y * y + z * z)
    mask = dens >= 0
    vevm = VolumeEVM(EVM.from_mask(mask), dens[mask], shape=mask.shape)
    sparse = _SamplingTable(vevm)
    stored = int((sparse.index >= 0).sum())
    # The sphere (13 voxels across) and its aprons touch at most 3 blocks per axis.
    assert stored <= 27
    assert sparse.table.nbytes == stored * BLOCK_VOXELS * 4
    dense_bytes = 8 * (n + 2) ** 3  # the complex64 dense table it replaced
    assert sparse.table.nbytes + sparse.index.nbytes < dense_bytes / 200
    estimate = _raycast.table_bytes(vevm, {"skip_empty": False}, navigate=False)
    assert sparse.table.nbytes + sparse.index.nbytes <= estimate < dense_bytes / 50
    # The same sphere in a grid 8 times larger: the table's pool does not grow.
    big = VolumeEVM(EVM.from_mask(mask), dens[mask], shape=(2 * n,) * 3)
    assert _SamplingTable(big).table.nbytes == sparse.table.nbytes
