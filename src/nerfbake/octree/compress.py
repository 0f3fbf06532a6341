"""``nerfbake octree compress``: the authors' web compression (``octree/compression.py``, svox's quantizer).

Leaves with sigma <= ``sigma_thresh`` are dropped (sigma 0, index 0). For every SH basis from ``retain`` on,
the RGB triples of the surviving leaves are median-cut quantised into a 2^bits float16 codebook with uint16
indices; the first ``retain`` bases are kept as float16. Arrays are DEFLATE-compressed. volrend hard-codes a
65 536-entry codebook stride, so ``bits`` must stay 16 for files meant for it.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nerfbake.octree.io import load_tree, write_npz
from nerfbake.progress import progress_bar


def median_cut(colors: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Codebook (2^bits, 3) and per-colour index (M,): split every cell at the median of its widest channel,
    ``bits`` times; entries are cell means (unused entries 0)."""
    m = colors.shape[0]
    x = colors.astype(np.float64)
    order = np.arange(m)
    bounds = np.array([0, m])
    for _ in range(bits):
        starts, ends = bounds[:-1], bounds[1:]
        sizes = ends - starts
        seg = np.repeat(np.arange(starts.size), sizes)
        v = x[order]
        nz = sizes > 0
        lo = np.zeros((starts.size, 3))
        hi = np.zeros((starts.size, 3))
        if m:
            lo[nz] = np.minimum.reduceat(v, starts[nz], axis=0)
            hi[nz] = np.maximum.reduceat(v, starts[nz], axis=0)
        axis = np.argmax(hi - lo, axis=1)
        span = (hi - lo)[np.arange(starts.size), axis]
        key = v[np.arange(m), axis[seg]]
        # one argsort orders every cell at once: cell id plus the value scaled into [0, 0.5)
        rank = seg + 0.5 * (key - lo[seg, axis[seg]]) / (span[seg] + 1e-300) * (1 - 1e-9)
        order = order[np.argsort(rank, kind="stable")]
        mids = starts + sizes // 2
        bounds = np.append(np.stack([starts, mids], 1).reshape(-1), m)
    starts, ends = bounds[:-1], bounds[1:]
    sizes = ends - starts
    codebook = np.zeros((starts.size, 3))
    nz = sizes > 0
    if m:
        codebook[nz] = np.add.reduceat(x[order], starts[nz], axis=0) / sizes[nz, None]
    index = np.empty(m, np.int64)
    index[order] = np.repeat(np.arange(starts.size), sizes)
    return codebook.astype(np.float32), index


def compress_tree(tree_path: str | Path, out: str | Path, bits: int = 16, retain: int = 0, sigma_thresh: float = 2.0) -> dict:
    start = time.time()
    if not 1 <= bits <= 16:
        raise ValueError(f"--bits must be in 1..16 (uint16 indices), got {bits}; volrend needs 16")
    tree = load_tree(tree_path)
    nb, n = tree.num_basis, tree.num_nodes
    if not 0 <= retain <= nb:
        raise ValueError(f"--retain {retain} is outside 0..{nb} (the tree has {nb} SH bases)")
    data = tree.data.numpy()
    sigma = data[..., -1]
    alive = (tree.child.numpy() == 0) & (sigma > sigma_thresh)
    if not alive.any():
        raise ValueError(f"{tree_path}: no leaf has sigma > {sigma_thresh}; lower --sigma-thresh")
    rgb = data[..., :-1].reshape(n, 2, 2, 2, 3, nb)  # [..., channel, basis]
    live = rgb[alive]  # (M, 3, B)
    quant_colors = np.zeros((nb - retain, 2 ** bits, 3), np.float16)
    quant_map = np.zeros((nb - retain, n, 2, 2, 2), np.uint16)
    with progress_bar("octree compress", nb - retain, unit="basis") as advance:
        for j in range(retain, nb):
            book, idx = median_cut(live[:, :, j], bits)
            quant_colors[j - retain] = book.astype(np.float16)
            quant_map[j - retain][alive] = idx.astype(np.uint16)
            advance()
    arrays = {
        "data_dim": np.array(tree.data_dim, dtype=np.int64),
        "child": tree.child.numpy().astype(np.int32),
        "invradius3": tree.invradius.numpy().astype(np.float32),
        "offset": tree.offset.numpy().astype(np.float32),
        "data_format": np.array(tree.data_format),
        "quant_colors": quant_colors,
        "quant_map": quant_map,
        "sigma": np.where(alive, sigma, 0).astype(np.float16),
    }
    if retain:
        kept = np.where(alive[..., None, None], rgb[..., :retain], 0)  # (n,2,2,2,3,R)
        arrays["data_retained"] = np.moveaxis(kept, -1, 0).astype(np.float16)  # (R,n,2,2,2,3)
    path = write_npz(out, arrays, compress=True)
    raw = Path(tree_path).stat().st_size
    return {"tree": str(path), "source": str(tree_path), "file_bytes": path.stat().st_size, "source_bytes": raw,
            "ratio": raw / path.stat().st_size, "bits": bits, "retain": retain, "sigma_thresh": sigma_thresh,
            "leaves_kept": int(alive.sum()), "seconds": time.time() - start}
