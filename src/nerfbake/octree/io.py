"""``.npz`` trees exactly as svox writes them and volrend reads them, raw or compressed.

Raw (svox ``N3Tree.save``): int64 ``data_dim``/``n_internal``/``n_free``/``depth_limit``, int32 ``child``
(relative pointers) and ``parent_depth``, float32 ``invradius3``/``offset``, float64 ``geom_resize_fact``, float16
``data`` and a unicode ``data_format``. Compressed (the authors' compression script): ``quant_colors`` float16
(B-R, K, 3), ``quant_map`` uint16 (B-R, n, 2, 2, 2), ``sigma`` float16, optional ``data_retained`` float16
(R, n, 2, 2, 2, 3), without ``data``. See ``shared/reference/plenoctree_anchors.md`` section 1.

nerfbake adds optional keys, which svox and volrend ignore (they load the arrays they know by name): ``env_map``,
uint8 (H, W, 3), the colour beyond the tree's box by direction (``render/envmap.py``), in either layout; and in
compressed trees ``compression``, a unicode JSON string recording how the file was compressed (bits per basis,
codebook, density threshold, the measured loss and its target) for ``octree info``.
"""
from __future__ import annotations

import ast
import json
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch

from nerfbake.atomic import atomic_file
from nerfbake.errors import NerfbakeError, reading
from nerfbake.eval.views import to_png
from nerfbake.octree.tree import N, Octree, basis_from_format


class OctreeFileError(NerfbakeError):
    """A tree file that cannot be read; the message names the file and what to do."""


def _fail(path, problem: str, fix: str = "write it with `nerfbake octree build` or svox's N3Tree.save") -> OctreeFileError:
    return OctreeFileError(f"{path}: {problem}; {fix}")


def env_map_arrays(tree: Octree) -> dict[str, np.ndarray]:
    """``{"env_map": uint8 (H, W, 3)}`` for a tree with an environment map, else nothing."""
    if tree.env_map is None:
        return {}
    return {"env_map": to_png(tree.env_map.detach().cpu().numpy())}


COMPRESSION_KEY = "compression"


def compression_record(path: str | Path) -> dict | None:
    """What ``octree compress`` recorded in a compressed tree (None for trees without the record)."""
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z[COMPRESSION_KEY])) if COMPRESSION_KEY in z.files else None


FLOAT16_MAX = float(np.finfo(np.float16).max)


def half_precision(values: np.ndarray, what: str) -> np.ndarray:
    """``values`` as float16, the precision volrend requires, saturated at +-65504. A teacher's density can exceed
    that (trunc_exp near a surface: the phone clip's tree held inf and its fine-tuning refused it); any density over
    a few hundred is opaque across a leaf already. NaN is a bug upstream and is refused, not written."""
    values = np.asarray(values, dtype=np.float32)
    if np.isnan(values).any():
        raise ValueError(f"refusing to save {what} holding NaN")
    return np.clip(values, -FLOAT16_MAX, FLOAT16_MAX).astype(np.float16)


def tree_arrays(tree: Octree) -> dict[str, np.ndarray]:
    """The svox key set for ``tree`` (what :func:`save_tree` writes), plus its environment map if it has one."""
    return {**env_map_arrays(tree), 
        "data_dim": np.array(tree.data_dim, dtype=np.int64),
        "child": tree.child.cpu().numpy().astype(np.int32),
        "parent_depth": tree.parent_depth(),
        "n_internal": np.array(tree.num_nodes, dtype=np.int64),
        "n_free": np.array(0, dtype=np.int64),
        "invradius3": tree.invradius.cpu().numpy().astype(np.float32),
        "offset": tree.offset.cpu().numpy().astype(np.float32),
        "depth_limit": np.array(tree.depth_limit, dtype=np.int64),
        "geom_resize_fact": np.array(1.0, dtype=np.float64),
        "data": half_precision(tree.data.detach().cpu().numpy(), "leaf data"),
        "data_format": np.array(tree.data_format),
    }


def write_npz(path: str | Path, arrays: dict[str, np.ndarray], compress: bool) -> Path:
    """Write atomically (temporary file in the same folder, then rename): no half-written trees."""
    path = Path(path)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        (np.savez_compressed if compress else np.savez)(f, **arrays)
    return path


def save_tree(tree: Octree, path: str | Path, compress: bool = False) -> Path:
    """svox's ``N3Tree.save``: ``np.savez`` (extraction/optimisation default) or DEFLATE with ``compress``."""
    if tree.num_leaves == 0:
        raise ValueError("refusing to save a tree with no leaves")
    return write_npz(path, tree_arrays(tree), compress)


def _open(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise OctreeFileError(f"{path}: no such tree file; build one with `nerfbake octree build`")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, EOFError, OSError) as exc:
        raise _fail(path, f"not a readable .npz (truncated or not a zip archive: {exc})") from None
    except ValueError as exc:
        raise _fail(path, f"holds an array numpy cannot read without pickle ({exc})") from None


def _want(path, z, key, kinds: str, ndim: int | None = None) -> np.ndarray:
    if key not in z:
        raise _fail(path, f"missing key {key!r} (keys present: {', '.join(sorted(z)) or 'none'}); this is not a PlenOctree file")
    a = z[key]
    if a.dtype.kind not in kinds:
        raise _fail(path, f"{key!r} has dtype {a.dtype}, expected kind {kinds!r} as svox writes it")
    if ndim is not None and a.ndim != ndim:
        raise _fail(path, f"{key!r} has shape {a.shape}, expected {ndim} dimensions")
    return a


def load_tree(path: str | Path, device="cpu") -> Octree:
    """Read a raw or compressed tree (ours, svox's, or the authors' compression script's). Anything wrong with the
    file is an :class:`OctreeFileError` naming it."""
    path = Path(path)
    with reading(path, OctreeFileError, "write it with `nerfbake octree build` or svox's N3Tree.save"):
        return _load_tree(path, device)


def _load_tree(path: Path, device) -> Octree:
    return tree_from_arrays(path, _open(path), device)


def tree_from_arrays(path, z: dict[str, np.ndarray], device="cpu") -> Octree:
    """The tree a file's arrays ``z`` describe (raw or compressed layout), checked; ``path`` names it in errors.
    Compression measures its candidates through this too, so what it measures is what a reader of the file gets."""
    child = _want(path, z, "child", "iu", 4)
    if child.dtype != np.int32:
        raise _fail(path, f"'child' is {child.dtype}; svox and volrend store relative pointers as int32")
    if child.shape[1:] != (N, N, N):
        raise _fail(path, f"'child' has shape {child.shape}; nerfbake (and volrend's viewers) need N = 2")
    data_dim_arr = _want(path, z, "data_dim", "iu")
    if data_dim_arr.size != 1 or not 1 <= int(data_dim_arr.reshape(-1)[0]) <= 4096:
        raise _fail(path, f"'data_dim' must be one positive integer, got shape {data_dim_arr.shape}")
    data_dim = int(data_dim_arr.reshape(-1)[0])
    fmt = str(z["data_format"]) if "data_format" in z else ("RGBA" if data_dim == 4 else f"SH{(data_dim - 1) // 3}")
    try:
        nb = basis_from_format(fmt, data_dim)
    except ValueError as exc:
        raise _fail(path, str(exc)) from None
    if "invradius3" in z:
        inv = _want(path, z, "invradius3", "f").astype(np.float32).reshape(-1)
    elif "invradius" in z:
        inv = np.full(3, float(z["invradius"]), np.float32)
    else:
        raise _fail(path, "missing 'invradius3' (or older 'invradius')")
    offset = _want(path, z, "offset", "f").astype(np.float32).reshape(-1)
    if inv.shape != (3,) or offset.shape != (3,) or not (np.all(np.isfinite(inv)) and np.all(inv > 0) and np.all(np.isfinite(offset))):
        raise _fail(path, f"bad bounding box (invradius3 {inv}, offset {offset})")
    if "quant_colors" in z:
        data = _decode_compressed(path, z, child.shape[0], nb)
    else:
        d = _want(path, z, "data", "f", 5)
        if d.dtype != np.float16:
            raise _fail(path, f"'data' is {d.dtype}; volrend requires half precision (svox saves .half())")
        if d.shape != (*child.shape, data_dim):
            raise _fail(path, f"'data' has shape {d.shape}, expected {(*child.shape, data_dim)} from 'child' and 'data_dim'")
        data = d.astype(np.float32)
    tree = Octree(
        child=torch.from_numpy(np.ascontiguousarray(child)), data=torch.from_numpy(np.ascontiguousarray(data)),
        offset=torch.from_numpy(offset.copy()), invradius=torch.from_numpy(inv.copy()),
        depth_limit=int(z["depth_limit"]) if "depth_limit" in z else -1,  # -1: taken from the tree below
    )
    if "env_map" in z:
        env = _want(path, z, "env_map", "u", 3)
        if env.dtype != np.uint8 or env.shape[2] != 3 or min(env.shape[:2]) < 1:
            raise _fail(path, f"'env_map' is {env.dtype} {env.shape}; nerfbake writes uint8 (H, W, 3)")
        tree.env_map = torch.from_numpy(env.astype(np.float32) / 255.0)
    _check_structure(path, tree)
    return tree.to(device)


def _decode_compressed(path, z, n: int, nb: int) -> np.ndarray:
    colors = _want(path, z, "quant_colors", "f", 3)
    qmap = _want(path, z, "quant_map", "u", 5)
    sigma = _want(path, z, "sigma", "f", 4)
    if colors.itemsize != 2:
        raise _fail(path, f"'quant_colors' is {colors.dtype}; volrend requires 2-byte (float16) codebooks")
    retained = z.get("data_retained")
    r = 0 if retained is None else retained.shape[0]
    if colors.shape[0] != nb - r or qmap.shape[0] != nb - r or colors.shape[2] != 3:
        raise _fail(path, f"codebooks {colors.shape} / map {qmap.shape} do not cover {nb} SH bases with {r} retained")
    if qmap.shape[1:] != (n, N, N, N) or sigma.shape != (n, N, N, N):
        raise _fail(path, f"'quant_map' {qmap.shape} or 'sigma' {sigma.shape} do not match {n} nodes")
    if int(qmap.max(initial=0)) >= colors.shape[1]:
        raise _fail(path, "'quant_map' indexes past the end of its codebook")
    rgb = np.empty((n, N, N, N, nb, 3), np.float32)
    if r:
        rgb[..., :r, :] = np.moveaxis(retained.astype(np.float32), 0, -2)
    for j in range(nb - r):
        rgb[..., r + j, :] = colors[j].astype(np.float32)[qmap[j]]
    data = np.empty((n, N, N, N, 3 * nb + 1), np.float32)
    data[..., :-1] = np.swapaxes(rgb, -1, -2).reshape(n, N, N, N, 3 * nb)
    data[..., -1] = sigma.astype(np.float32)
    return data


def _check_structure(path, tree: Octree) -> None:
    """Pointers stay inside the array and reach every node once; there are leaves; values are finite. Fills in
    ``depth_limit`` when the file has none (-1)."""
    flat = tree.child.reshape(-1).numpy().astype(np.int64)
    n = tree.num_nodes
    if n == 0:
        raise _fail(path, "the tree has no nodes")
    slots = np.nonzero(flat)[0]
    targets = slots // 8 + flat[slots]
    if targets.size and (targets.min() <= 0 or targets.max() >= n):
        raise _fail(path, "a child pointer points outside the node array (corrupt 'child')")
    if np.unique(targets).size != targets.size:
        raise _fail(path, "two cells point at the same child node (corrupt 'child')")
    if tree.num_leaves == 0:
        raise _fail(path, "the tree has no leaves")
    depth = int(tree.parent_depth()[:, 1].max())  # safe now: every node has one parent, none points at the root
    if tree.depth_limit < 0:
        tree.depth_limit = depth
    if depth > tree.depth_limit + 1 or tree.depth_limit > 23:
        raise _fail(path, f"the tree is deeper than its depth_limit {tree.depth_limit} (or deeper than 24 levels)")
    if not torch.isfinite(tree.data).all():
        raise _fail(path, "leaf data holds NaN or infinite values")


# --- volrend's loader rules (patched cnpy): a check our writer's files are run through in the tests ---------------------

def volrend_problems(path: str | Path) -> list[str]:
    """Reasons volrend's ``N3Tree::load_npz`` would reject or misread ``path`` (empty list = loadable).

    Reads the zip the way volrend's cnpy does: local headers only, STORE or DEFLATE, no data descriptors, npy 1.0
    headers, little-endian arrays; then the key and dtype rules of section 1c of the reference notes."""
    problems: list[str] = []
    arrays: dict[str, tuple[str, tuple]] = {}
    raw = Path(path).read_bytes()
    pos = 0
    while pos + 4 <= len(raw) and raw[pos:pos + 4] == b"PK\x03\x04":
        (flags, method, csize, usize, nlen, xlen) = struct.unpack_from("<2xHH8xII HH", raw, pos + 4)
        name = raw[pos + 30: pos + 30 + nlen].decode()
        extra = raw[pos + 30 + nlen: pos + 30 + nlen + xlen]
        if flags & 0x8:
            problems.append(f"{name}: zip entry uses a data descriptor (cnpy cannot read it)")
        if method not in (0, 8):
            problems.append(f"{name}: compression method {method} (cnpy reads STORE and DEFLATE only)")
        if csize == 0xFFFFFFFF:  # zip64 local extra: [id 1, size, usize, csize]
            usize, csize = struct.unpack_from("<QQ", extra, 4)
        body = raw[pos + 30 + nlen + xlen: pos + 30 + nlen + xlen + csize]
        if method == 8:
            body = zlib.decompress(body, -15)
        pos += 30 + nlen + xlen + csize
        if body[:6] != b"\x93NUMPY":
            problems.append(f"{name}: not an npy array")
            continue
        if body[6] != 1:
            problems.append(f"{name}: npy format version {body[6]}.{body[7]} (cnpy reads 1.0 only)")
            continue
        hlen = struct.unpack_from("<H", body, 8)[0]
        header = ast.literal_eval(body[10:10 + hlen].decode("latin1"))
        descr, shape = header["descr"], tuple(header["shape"])
        if header["fortran_order"]:
            problems.append(f"{name}: Fortran order")
        if descr[0] == ">":
            problems.append(f"{name}: big-endian data")
        arrays[name[:-4] if name.endswith(".npy") else name] = (descr, shape)
    if not arrays:
        return ["not a zip archive of npy arrays"]
    need = {"data_dim": "<i8", "child": "<i4", "offset": "<f4"}
    for key, descr in need.items():
        if key not in arrays:
            problems.append(f"missing {key}")
        elif arrays[key][0] != descr:
            problems.append(f"{key} is {arrays[key][0]}, volrend reads {descr}")
    if "invradius3" in arrays:
        if arrays["invradius3"][0] != "<f4":
            problems.append(f"invradius3 is {arrays['invradius3'][0]}, volrend reads <f4")
    elif "invradius" not in arrays or arrays["invradius"][0] != "<f8":
        problems.append("missing invradius3 (float32) or invradius (float64)")
    if "data_format" in arrays and not arrays["data_format"][0].startswith("<U"):
        problems.append("data_format must be a numpy unicode string")
    if "quant_colors" in arrays:
        if arrays["quant_colors"][0] != "<f2":
            problems.append("quant_colors must be float16")
        elif arrays["quant_colors"][1][1] != 65536:
            problems.append("quant_colors must have 65536 entries per basis (volrend hard-codes the stride: --bits 16)")
        if arrays.get("quant_map", ("", ()))[0] != "<u2":
            problems.append("quant_map must be uint16")
        if arrays.get("sigma", ("", ()))[0] != "<f2":
            problems.append("sigma must be float16")
    elif arrays.get("data", ("", ()))[0] != "<f2":
        problems.append("data must be stored in half precision (float16)")
    return problems


def tree_info(path: str | Path) -> dict:
    """What ``nerfbake octree info`` prints: sizes, leaves per depth, bounds, and volrend's loader rules checked."""
    tree = load_tree(path)
    lo, hi = tree.world_bounds
    leaves = tree.leaves()
    return {
        "tree": str(path), "data_format": tree.data_format, "data_dim": tree.data_dim, "sh_degree": tree.sh_degree,
        "num_nodes": tree.num_nodes, "num_leaves": tree.num_leaves, "depth_limit": tree.depth_limit,
        "leaves_per_depth": {int(d): int((leaves["depth"] == d).sum()) for d in leaves["depth"].unique()},
        "nonzero_sigma_leaves": int((tree.data.reshape(-1, tree.data_dim)[leaves["index"], -1] > 0).sum()),
        "box_min": lo.tolist(), "box_max": hi.tolist(), "file_bytes": Path(path).stat().st_size,
        "env_map": None if tree.env_map is None else list(tree.env_map.shape[:2]),
        "volrend_problems": volrend_problems(path), "compression": compression_record(path),
    }
