"""Vertex positions from a PLY file (the sparse point cloud nerfstudio's ``ply_file_path`` and ``nerfbake process``
write): ascii or binary, any vertex properties, only x, y, z kept."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfbake.data.errors import DatasetError
from nerfbake.errors import reading

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}


def read_ply_points(path: Path) -> np.ndarray:
    """(N, 3) float64 vertex positions; a clear error for a file that is not a readable PLY point list."""
    path = Path(path)
    with reading(path, DatasetError, "re-export the point cloud (e.g. `nerfbake process` writes one)"):
        points = _read_ply_points(path)
    bad = ~np.isfinite(points).all(-1)
    if bad.any():
        raise DatasetError(f"{path}: {int(bad.sum())} of {len(points)} points are NaN or infinite (first at vertex "
                           f"{int(np.argmax(bad))}); remove them or re-export the point cloud")
    return points


def _read_ply_points(path: Path) -> np.ndarray:
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: not a PLY file (no 'ply' magic or no end_header); re-export the point cloud")
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[data.index(b"\n", end) + 1:]
    fmt, count, props, in_vertex, before = None, 0, [], False, 0
    for line in header:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            in_vertex = words[1] == "vertex"
            if in_vertex:
                count = int(words[2])
            elif count == 0:
                before += 1  # an element ahead of the vertices: not supported below
        elif words[0] == "property" and in_vertex:
            if words[1] == "list" or words[1] not in _TYPES:
                raise DatasetError(f"{path}: unsupported vertex property {' '.join(words[1:])!r}")
            props.append((words[2], _TYPES[words[1]]))
    names = [p[0] for p in props]
    if before or not all(k in names for k in "xyz"):
        raise DatasetError(f"{path}: expected a vertex element first with x, y, z properties")
    if fmt == "ascii":
        rows = body.decode("ascii", "replace").split("\n")[:count]
        table = np.array([r.split()[: len(names)] for r in rows], dtype=np.float64)
        if table.shape != (count, len(names)):
            raise DatasetError(f"{path}: {count} vertices announced but the file is truncated")
        cols = {n: table[:, i] for i, n in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(body) < count * dtype.itemsize:
            raise DatasetError(f"{path}: {count} vertices announced but the file is truncated")
        cols = np.frombuffer(body, dtype=dtype, count=count)
    else:
        raise DatasetError(f"{path}: unknown PLY format {fmt!r}")
    return np.stack([np.asarray(cols[k], dtype=np.float64) for k in "xyz"], axis=-1)
