"""``nerfbake octree compress``: the authors' web compression (``octree/compression.py``, svox's quantizer), with
the bits per SH band chosen by measured error.

The layout is the authors': leaves with sigma <= ``sigma_thresh`` are dropped (sigma 0, index 0); for every SH
basis from ``retain`` on, the RGB triples of the surviving leaves are quantised into a 2^bits float16 codebook with
uint16 indices; the first ``retain`` bases are kept as float16; arrays are DEFLATE-compressed. volrend hard-codes a
65 536-entry codebook stride, so ``bits`` must stay 16 for files meant for it.

Three departures, each keeping the file volrend's:

* Higher SH bands may use fewer of the 65 536 entries (the rest stay zero). Median cut gives every entry the same
  number of leaves, so a 16-bit index costs about 16 bits even after DEFLATE; the small view-dependent bands of a
  matte scene lose little at 8/6/4 bits, whose indices cost a byte or less.
* How few is measured, not assumed (``--target-db``): a glossy scene keeps its look in exactly the bands a fixed
  allocation squeezes hardest. The candidates are rendered from a few training views with the same reader a file
  goes through, and the smallest within the target is written (:func:`choose_allocation`).
* Median cut is refined by a few k-means steps (:func:`kmeans_refine`): lower error at the same entry count, and
  an uneven index histogram that DEFLATE shrinks.
"""
from __future__ import annotations

import itertools
import json
import time
import zlib
from pathlib import Path

import numpy as np

from nerfbake.data.formats import load_dataset
from nerfbake.octree.evaluate import ViewLoss
from nerfbake.octree.io import COMPRESSION_KEY, env_map_arrays, half_precision, load_tree, tree_from_arrays, write_npz
from nerfbake.octree.tree import Octree
from nerfbake.progress import progress_bar
from nerfbake.render.sh import sh_num_coeffs


def median_cut(colors: np.ndarray, bits: int, min_extent: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Codebook (2^bits, 3) and per-colour index (M,): split every cell at the median of its widest channel,
    ``bits`` times; entries are cell means (unused entries 0). Cells whose widest extent is already below
    ``min_extent`` are not split: their colours share one entry, which costs nothing visible and lets DEFLATE
    shrink the index maps (the authors' quantiser always splits, spending 16 bits on near-identical values)."""
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
        mids = np.where(span < min_extent, ends, starts + sizes // 2)
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


def kmeans_refine(colors: np.ndarray, codebook: np.ndarray, index: np.ndarray, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd iterations from a median-cut start: every colour moves to its nearest used entry, every entry to the
    mean of its colours. Median cut gives each entry the same number of colours, spending entries on dense clumps
    of near-identical residuals; k-means moves them to where the error is, and the uneven index histogram it leaves
    lets DEFLATE shrink the map. Unused entries stay unused (0)."""
    from scipy.spatial import cKDTree

    x = colors.astype(np.float64)
    book = codebook.astype(np.float64)
    k = len(book)
    for _ in range(iters):
        used = np.nonzero(np.bincount(index, minlength=k))[0]
        if used.size < 2:
            break
        index = used[cKDTree(book[used]).query(x, workers=-1)[1]]
        book = cell_means(x, index, book)
    return book.astype(np.float32), index


def cell_means(colors: np.ndarray, index: np.ndarray, book: np.ndarray) -> np.ndarray:
    """``book`` (K, 3) float64 with every entry that has colours (M, 3) assigned by ``index`` (M,) moved to their
    mean; entries without any keep their value."""
    counts = np.bincount(index, minlength=len(book))
    nz = counts > 0
    for c in range(3):
        book[nz, c] = np.bincount(index, weights=colors[:, c].astype(np.float64), minlength=len(book))[nz] / counts[nz]
    return book


MIN_EXTENT = 2.0 ** -9  # about float16's spacing at 1: finer splits would quantise rounding noise
BAND_BITS = (16, 8, 6, 4)  # codebook bits for SH bands 0, 1, 2, 3 when there are no photos to measure the loss on
BITS_LADDER = (16, 12, 10, 8, 7, 6, 5, 4, 3, 2)  # what --target-db tries for a band, one rung at a time
SIGMA_LADDER = (2.0, 4.0)  # and then for the density below which leaves are dropped, times --sigma-thresh
SIGMA_LOWER = (0.5, 0.25, 0.0)  # tried first, in turn, while dropping leaves alone costs over half of --target-db
CODEBOOKS = ("kmeans", "median")
KMEANS_ITERS = 4
TARGET_DB = 0.5
QUALITY_FLOOR_DB = 25.0  # added error is charged as if the tree scored at least this (evaluate.ViewLoss)
MEASURE_VIEWS = 4


def basis_bits(num_basis: int, bits: int, band_bits) -> list[int]:
    """Codebook bits for each SH basis: basis j is in band floor(sqrt(j)); never more than ``bits``."""
    band_bits = list(band_bits) if band_bits else [bits]
    return [min(bits, band_bits[min(int(j ** 0.5), len(band_bits) - 1)]) for j in range(num_basis)]


def _deflated_bytes(a: np.ndarray) -> int:
    """What DEFLATE (numpy's savez_compressed: zlib level 6) makes of ``a`` on its own."""
    return len(zlib.compress(np.ascontiguousarray(a).tobytes(), 6))


class Quantizer:
    """The surviving leaves of one tree and the codebook and index map of each SH basis at each bit count, fitted
    once and shared by every allocation ``--target-db`` tries and by the file finally written. Median cut splits
    every cell in two per bit, so one ``bits``-deep cut holds every shallower one (index >> (bits - b)); k-means
    refines a (basis, bits) when ``codebook`` is ``'kmeans'`` (the search sets it to ``'median'``: cheap fits)."""

    def __init__(self, tree: Octree, nb: int, bits: int, sigma_thresh: float, min_extent: float, codebook: str):
        if codebook not in CODEBOOKS:
            raise ValueError(f"unknown codebook {codebook!r}; choose one of {', '.join(CODEBOOKS)}")
        self.tree, self.nb, self.bits, self.codebook, self.min_extent = tree, nb, bits, codebook, min_extent
        data = tree.data.cpu().numpy()
        self.sigma = data[..., -1]
        self.alive = (tree.child.cpu().numpy() == 0) & (self.sigma > sigma_thresh)
        self.rgb = data[..., :-1].reshape(*self.sigma.shape, 3, tree.num_basis)[..., :nb]  # [..., channel, basis]
        self.live = self.rgb[self.alive]  # (M, 3, B)
        self._cuts: dict[int, np.ndarray] = {}
        self._fits: dict[tuple[str, int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._sizes: dict[tuple[str, int, int], int] = {}
        self._decoded: Octree | None = None
        self._decoded_state: dict = {}

    def fit(self, j: int, bits: int) -> tuple[np.ndarray, np.ndarray]:
        """float16 codebook (2^bits, 3) and uint16 index per surviving leaf for basis ``j``."""
        key = (self.codebook, j, bits)
        if key not in self._fits:
            colors = self.live[:, :, j]
            if j not in self._cuts:
                self._cuts[j] = median_cut(colors, self.bits, self.min_extent)[1]
            idx = self._cuts[j] >> (self.bits - bits)
            book = cell_means(colors, idx, np.zeros((2 ** bits, 3)))
            if self.codebook == "kmeans":
                book, idx = kmeans_refine(colors, book, idx, KMEANS_ITERS)
            self._fits[key] = book.astype(np.float16), idx.astype(np.uint16)
        return self._fits[key]

    def alive_above(self, sigma_thresh: float) -> np.ndarray:
        return self.alive & (self.sigma > sigma_thresh)

    def index_map(self, j: int, bits: int, alive: np.ndarray) -> np.ndarray:
        """Basis ``j``'s uint16 map over every cell (0 where no surviving leaf), as ``quant_map[j]`` stores it."""
        qmap = np.zeros(self.alive.shape, np.uint16)
        qmap[self.alive] = self.fit(j, bits)[1]
        qmap[~alive] = 0
        return qmap

    def arrays(self, per_basis: list[int], retain: int, sigma_thresh: float) -> dict[str, np.ndarray]:
        """The compressed web layout's arrays for this allocation: what is written."""
        n, nb, tree = self.tree.num_nodes, self.nb, self.tree
        alive = self.alive_above(sigma_thresh)
        quant_colors = np.zeros((nb - retain, 2 ** self.bits, 3), np.float16)
        quant_map = np.zeros((nb - retain, n, 2, 2, 2), np.uint16)
        for j in range(retain, nb):
            book = self.fit(j, per_basis[j])[0]
            quant_colors[j - retain, :len(book)] = book
            quant_map[j - retain] = self.index_map(j, per_basis[j], alive)
        arrays = {
            "data_dim": np.array(3 * nb + 1, dtype=np.int64),
            "child": tree.child.cpu().numpy().astype(np.int32),
            "invradius3": tree.invradius.cpu().numpy().astype(np.float32),
            "offset": tree.offset.cpu().numpy().astype(np.float32),
            "data_format": np.array(f"SH{nb}"),
            "quant_colors": quant_colors,
            "quant_map": quant_map,
            "sigma": half_precision(np.where(alive, self.sigma, 0), "densities"),
            **env_map_arrays(tree),
        }
        if retain:
            kept = np.where(alive[..., None, None], self.rgb[..., :retain], 0)  # (n,2,2,2,3,R)
            arrays["data_retained"] = np.moveaxis(kept, -1, 0).astype(np.float16)  # (R,n,2,2,2,3)
        return arrays

    def decoded(self, per_basis: list[int], retain: int, sigma_thresh: float) -> Octree:
        """The tree a reader of :meth:`arrays` gets, without writing or decoding the whole file per candidate: the
        first call goes through the reader (``tree_from_arrays``), later ones re-decode only the bases whose codebook
        changed, as the reader would (``quant_colors[j][quant_map[j]]``), and the densities if the threshold did."""
        state = {"retain": retain, "sigma": sigma_thresh,
                 **{j: (self.codebook, per_basis[j]) for j in range(retain, self.nb)}}
        if self._decoded is None or self._decoded_state["retain"] != retain:
            self._decoded = tree_from_arrays("<candidate>", self.arrays(per_basis, retain, sigma_thresh))
            self._decoded_state = state
            return self._decoded
        data = self._decoded.data.numpy()
        alive = self.alive_above(sigma_thresh)
        threshold_changed = self._decoded_state["sigma"] != sigma_thresh
        if threshold_changed:
            data[..., -1] = half_precision(np.where(alive, self.sigma, 0), "densities").astype(np.float32)
            for j in range(retain):
                kept = np.where(alive[..., None], self.rgb[..., j], 0).astype(np.float16)
                data[..., j::self.nb][..., :3] = kept.astype(np.float32)
        for j in range(retain, self.nb):
            if threshold_changed or self._decoded_state[j] != state[j]:
                book = self.fit(j, per_basis[j])[0].astype(np.float32)
                data[..., j::self.nb][..., :3] = book[self.index_map(j, per_basis[j], alive)]
        self._decoded_state = state
        return self._decoded

    def basis_bytes(self, j: int, bits: int) -> int:
        """DEFLATE size of basis ``j``'s surviving indices and codebook: what an allocation changes, basis by basis
        (the dropped cells' zeros between them cost next to nothing)."""
        key = (self.codebook, j, bits)
        if key not in self._sizes:
            book, idx = self.fit(j, bits)
            self._sizes[key] = _deflated_bytes(idx) + _deflated_bytes(book)
        return self._sizes[key]

    def estimated_bytes(self, per_basis: list[int], retain: int) -> int:
        return sum(self.basis_bytes(j, per_basis[j]) for j in range(retain, self.nb))


def settle_threshold(tree: Octree, nb: int, bits: int, sigma_thresh: float, min_extent: float, loss: ViewLoss,
                     retain: int, target_db: float) -> tuple[Quantizer, float, list[dict]]:
    """The quantiser the allocation search starts from: at ``sigma_thresh``, unless dropping the leaves at or under
    it costs more than half of ``target_db`` with every basis at full bits, leaving the bands too little to spend
    (the phone clip's tree, its floor made of faint leaves: 0.46 of 0.5 dB gone at sigma 2, so every band kept 16
    bits and the file 10 MB); then the first of the lower thresholds (:data:`SIGMA_LOWER`) that costs at most half,
    or the cheapest tried. Median-cut codebooks; returns the quantiser, its threshold and the measurements."""
    tried, best = [], None
    with progress_bar("octree compress: settling the density threshold", 1 + len(SIGMA_LOWER), unit="try") as advance:
        for m in (1.0,) + SIGMA_LOWER:
            thresh = m * sigma_thresh
            q = Quantizer(tree, nb, bits, thresh, min_extent, "median")
            if q.alive.any():  # fitting every basis's deep cut: minutes for millions of leaves
                value = loss(q.decoded(basis_bits(nb, bits, None), retain, thresh))
                tried.append({"band_bits": [bits], "sigma_thresh": thresh, "codebook": "median", "loss_db": value,
                              "bytes_est": q.estimated_bytes(basis_bits(nb, bits, None), retain)})
                if best is None or value < best[2]:
                    best = (q, thresh, value)
            advance()
            if best is not None and best[2] <= target_db / 2:
                break
    return best[0], best[1], tried


def choose_allocation(q: Quantizer, loss: ViewLoss, retain: int, sigma_thresh: float, target_db: float) -> dict:
    """The smallest allocation of bits per SH band within ``target_db``. The search runs on median-cut codebooks
    (cheap: one deep cut per basis serves every rung). Each band is measured alone, one rung down the ladder at a
    time with the others at full bits, until it alone breaks the target; small losses from different bands add
    (their errors are independent), so the sum of each band's own loss predicts a combination's, and the smallest
    combination predicted within budget is measured; if it overshoots, the budget for the predicted excess shrinks
    by the ratio of the target's excess to the measured one and the next is measured (three tries). Then the
    density threshold is raised while the loss allows, and last the chosen allocation is refitted with k-means (when
    asked) and kept if it still meets the target (it usually loses less)."""
    nb, bits = q.nb, q.bits
    bands = int(round(nb ** 0.5))
    quantised = [band for band in range(bands) if (band + 1) ** 2 > retain]  # a band wholly retained has no codebook
    rungs = [bits] + [b for b in BITS_LADDER if b < bits]
    per_basis = lambda bb: basis_bits(nb, bits, bb)  # noqa: E731
    final_codebook, q.codebook = q.codebook, "median"
    tried = []

    def measure(band_bits: list[int], thresh: float) -> float:
        value = loss(q.decoded(per_basis(band_bits), retain, thresh))
        tried.append({"band_bits": list(band_bits), "sigma_thresh": thresh, "codebook": q.codebook, "loss_db": value,
                      "bytes_est": q.estimated_bytes(per_basis(band_bits), retain)})
        advance()
        return value

    def band_bytes(band: int, b: int) -> int:
        return sum(q.basis_bytes(j, b) for j in range(max(band * band, retain), (band + 1) ** 2))

    top = [bits] * bands
    attempts = 3
    with progress_bar("octree compress: measuring allocations", 2 + len(quantised) * (len(rungs) - 1) + attempts
                      + len(SIGMA_LADDER), unit="try") as advance:
        base = measure(top, sigma_thresh)
        excess = {band: {bits: 0.0} for band in range(bands)}
        for band in quantised:
            for b in rungs[1:]:
                trial = top.copy()
                trial[band] = b
                value = measure(trial, sigma_thresh)
                if value > target_db:
                    break  # lower rungs lose more still
                excess[band][b] = max(value - base, 0.0)
        options = [sorted(excess[band].items(), key=lambda kv: -kv[0]) for band in range(bands)]
        band_bits, current, budget = top, base, target_db
        for _ in range(attempts):
            best = None
            for combo in itertools.product(*options):
                if base + sum(e for _, e in combo) > budget:
                    continue
                size = sum(band_bytes(band, b) for band, (b, _) in enumerate(combo))
                if best is None or size < best[0]:
                    best = (size, [b for b, _ in combo])
            if best is None or best[1] == top:
                break
            value = measure(best[1], sigma_thresh)
            if value <= target_db:
                band_bits, current = best[1], value
                break
            # bands' losses add while small but compound when large: shrink the budget for their sum by how much
            # the prediction fell short (a phone clip's tree predicted 0.45 dB for 2-3 bits everywhere, measured 0.94)
            budget = base + (budget - base) * 0.95 * (target_db - base) / (value - base)
        for thresh in [m * sigma_thresh for m in SIGMA_LADDER]:
            value = measure(band_bits, thresh)
            if value > target_db:
                break
            sigma_thresh, current = thresh, value
        if final_codebook != q.codebook:
            q.codebook = final_codebook
            value = measure(band_bits, sigma_thresh)
            if value <= max(target_db, current):
                current = value
            else:
                q.codebook = "median"
    return {"bits_per_band": band_bits, "sigma_thresh": sigma_thresh, "measured_loss_db": current,
            "measured_on": f"{len(loss.frames)} training views", "target_db": target_db,
            "target_met": current <= target_db, "tried": tried}


def compress_tree(tree_path: str | Path, out: str | Path, bits: int = 16, retain: int = 0, sigma_thresh: float = 2.0,
                  sh_degree: int | None = None, min_extent: float = MIN_EXTENT, band_bits=None,
                  data: str | Path | None = None, target_db: float = TARGET_DB, downscale: float = 1.0,
                  normalize: str = "auto", views: int = MEASURE_VIEWS, codebook: str = "kmeans") -> dict:
    """Without ``band_bits`` and with the training photos (``data``), the bits per SH band and the density threshold
    are chosen by measured error: the smallest file whose PSNR on ``views`` training views is within ``target_db``
    of the uncompressed tree's. ``band_bits`` fixes them (``(bits,)`` with ``codebook='median'`` is the authors'
    quantiser); without ``data`` they fall back to :data:`BAND_BITS`. ``sh_degree`` below the tree's drops the
    higher SH bands first (the volrend author's advice for trees too large for WebGL is SH9)."""
    start = time.time()
    if not 1 <= bits <= 16:
        raise ValueError(f"--bits must be in 1..16 (uint16 indices), got {bits}; volrend needs 16")
    if band_bits is not None and not all(1 <= b <= 16 for b in band_bits):
        raise ValueError(f"--band-bits must be in 1..16, got {list(band_bits)}")
    if not target_db > 0:
        raise ValueError(f"--target-db must be positive, got {target_db}")
    tree = load_tree(tree_path)
    if sh_degree is not None and not 0 <= sh_degree <= tree.sh_degree:
        raise ValueError(f"--sh-degree {sh_degree} is outside 0..{tree.sh_degree} (the degree this tree holds)")
    nb = tree.num_basis if sh_degree is None else sh_num_coeffs(sh_degree)
    if not 0 <= retain <= nb:
        raise ValueError(f"--retain {retain} is outside 0..{nb} (the tree has {nb} SH bases)")
    q = Quantizer(tree, nb, bits, sigma_thresh, min_extent, codebook)
    if not q.alive.any():
        raise ValueError(f"{tree_path}: no leaf has sigma > {sigma_thresh}; lower --sigma-thresh")
    if band_bits is None and data is not None:
        loss = ViewLoss(tree, load_dataset(data, downscale=downscale, normalize=normalize), views,
                        quality_floor_db=QUALITY_FLOOR_DB)
        q, sigma_thresh, settling = settle_threshold(tree, nb, bits, sigma_thresh, min_extent, loss, retain, target_db)
        q.codebook = codebook
        choice = choose_allocation(q, loss, retain, sigma_thresh, target_db)
        band_bits, sigma_thresh = choice["bits_per_band"], choice["sigma_thresh"]
        choice["allocation"] = "measured"
        choice["tried"] = settling + choice["tried"]
    else:
        choice = {"allocation": "fixed" if band_bits is not None else "fixed (no --data to measure on)"}
        band_bits = BAND_BITS if band_bits is None else band_bits
    per_basis = basis_bits(nb, bits, band_bits)
    with progress_bar("octree compress", nb - retain, unit="basis") as advance:
        for j in range(retain, nb):
            q.fit(j, per_basis[j])
            advance()
    summary = {"bits": bits, "band_bits": per_basis[retain:], "retain": retain, "sigma_thresh": sigma_thresh,
               "data_format": f"SH{nb}", "min_extent": min_extent, "codebook": q.codebook,
               "leaves_kept": int(q.alive_above(sigma_thresh).sum()), **choice}
    kept = {k: v for k, v in summary.items() if k != "tried"}
    path = write_npz(out, {**q.arrays(per_basis, retain, sigma_thresh), COMPRESSION_KEY: np.array(json.dumps(kept))},
                     compress=True)
    raw = Path(tree_path).stat().st_size
    return {"tree": str(path), "source": str(tree_path), "file_bytes": path.stat().st_size, "source_bytes": raw,
            "ratio": raw / path.stat().st_size, "seconds": time.time() - start, **summary}
