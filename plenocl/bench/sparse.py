"""The weight matrix stored explicitly (``scipy.sparse``), for small grids only.

plenocl never needs it: the projector is matrix-free. It exists as the baseline that
benchmarks compare against, and for tests that want ``W`` itself.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def weight_matrix(projector, batch: int = 2500) -> sp.csr_matrix:
    """The projector's weights as a CSR matrix (pixels x voxels, float32).

    Built from the footprint kernel's products, ``batch`` voxels at a time. Memory
    grows with the number of non-zeros (about a thousand per voxel): keep grids small.
    """
    vox = np.array(list(np.ndindex(*projector.shape)))
    n_pix = int(np.prod(projector.image_shape))
    blocks = []
    for start in range(0, len(vox), batch):
        idx, w = projector.footprint_entries(vox[start:start + batch])
        keep = idx >= 0
        col = np.broadcast_to(np.arange(len(idx))[:, None], idx.shape)[keep]
        block = sp.csc_matrix((w[keep], (idx[keep], col)), shape=(n_pix, len(idx)))
        block.eliminate_zeros()
        blocks.append(block)
    return sp.hstack(blocks, format="csr", dtype=np.float32)


def matrix_bytes(a: sp.csr_matrix) -> int:
    """Bytes a CSR matrix holds (data, indices, row pointers)."""
    return a.data.nbytes + a.indices.nbytes + a.indptr.nbytes
