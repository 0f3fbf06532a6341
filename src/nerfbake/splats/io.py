"""The two files splat tools read.

* ``.ply``, the 3DGS reference code's layout: one ``vertex`` element of little-endian float32 properties
  ``x y z nx ny nz f_dc_0..2 f_rest_0..(3(B-1)-1) opacity scale_0..2 rot_0..3`` (normals zero; ``f_rest`` channel
  by channel: all of red's higher coefficients, then green's, then blue's; opacity pre-sigmoid; log scales;
  w-first quaternions). Degree 3 has 45 ``f_rest`` properties.
* ``.splat``, the compact web layout (antimatter15's viewer and its descendants): 32 bytes per splat, position
  3 x float32, linear scale 3 x float32, RGBA 4 x uint8 (the degree-0 colour and the opacity), rotation 4 x uint8
  (w-first quaternion mapped from [-1, 1] to 0..255), most visible splats first.

Beside either, ``<name>.json`` records the frame: the matrix that takes the splats back to the input photos'
coordinates, which exporters that drop it leave users to guess.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfbake.atomic import atomic_file
from nerfbake.errors import NerfbakeError
from nerfbake.splats.gaussians import SH_C0, Gaussians


class SplatFileError(NerfbakeError):
    """A splat file that cannot be written or read; names the file and the fix."""


SPLAT_RECORD = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def ply_properties(sh_degree: int) -> list[str]:
    """The reference layout's property names, in file order."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def ply_bytes(g: Gaussians) -> bytes:
    """The whole ``.ply`` file of ``g``."""
    names = ply_properties(g.sh_degree)
    rest = g.sh[:, :, 1:].reshape(len(g), -1)  # (N, 3 * (B - 1)): channel-major, as the reference transposes it
    table = np.concatenate([g.means, np.zeros_like(g.means), g.sh[:, :, 0], rest, g.opacity_logits[:, None],
                            g.log_scales, g.quats], 1).astype("<f4")
    assert table.shape[1] == len(names)
    header = "\n".join(["ply", "format binary_little_endian 1.0", "comment written by nerfbake export",
                        f"element vertex {len(g)}", *[f"property float {n}" for n in names], "end_header"]) + "\n"
    return header.encode("ascii") + np.ascontiguousarray(table).tobytes()


def splat_bytes(g: Gaussians) -> bytes:
    """The whole ``.splat`` file of ``g`` (sorted by the web viewer's order: larger, more opaque splats first)."""
    scales = np.exp(g.log_scales)
    order = np.argsort(-(scales.prod(1) * g.opacities), kind="stable")
    record = np.zeros(len(g), dtype=SPLAT_RECORD)
    record["pos"] = g.means[order]
    record["scale"] = scales[order]
    rgba = np.concatenate([g.base_colors[order], g.opacities[order, None]], 1)
    record["rgba"] = np.clip(np.round(rgba * 255), 0, 255)
    q = g.quats[order] / np.linalg.norm(g.quats[order], axis=1, keepdims=True)
    record["rot"] = np.clip(np.round(q * 128 + 128), 0, 255)
    return record.tobytes()


FORMATS = {"ply": ply_bytes, "splat": splat_bytes}


def check_format(path, fmt: str) -> None:
    if fmt not in FORMATS:
        raise SplatFileError(f"{path}: unknown splat format {fmt!r}; choose {' or '.join(FORMATS)}")


def write_splats(g: Gaussians, path: str | Path, fmt: str) -> Path:
    """Write ``g`` in ``fmt`` (``ply`` or ``splat``) at ``path``, whole or not at all."""
    check_format(path, fmt)
    if len(g) == 0:
        raise SplatFileError(f"{path}: no Gaussians to write (the scene is empty); check the tree with nerfbake octree info")
    data = FORMATS[fmt](g)
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def read_ply(path: str | Path) -> Gaussians:
    """Gaussians from a reference-layout ``.ply`` (ours or another exporter's float32 files)."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise SplatFileError(f"{path}: not a PLY file (no 'ply' magic or end_header); give a 3DGS .ply")
    header = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise SplatFileError(f"{path}: only binary little-endian PLY is read; convert it or re-export it")
    names = [line.split()[2] for line in header if line.startswith("property float ")]
    count = next((int(line.split()[2]) for line in header if line.startswith("element vertex ")), None)
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    basis = len(rest) // 3 + 1
    if count is None or len(names) != sum(line.startswith("property ") for line in header) or basis not in (1, 4, 9, 16):
        raise SplatFileError(f"{path}: not the 3DGS layout (float properties x..rot_3 with 0, 9, 24 or 45 f_rest)")
    table = np.frombuffer(raw, "<f4", count * len(names), end + len("end_header\n")).reshape(count, len(names))
    col = {n: table[:, i].astype(np.float64) for i, n in enumerate(names)}

    def stack(keys):
        return np.stack([col[k] for k in keys], 1)

    sh = stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, :, None]
    if rest:
        sh = np.concatenate([sh, stack(rest).reshape(count, 3, basis - 1)], 2)
    return Gaussians(stack("xyz"), stack(["scale_0", "scale_1", "scale_2"]),
                     stack(["rot_0", "rot_1", "rot_2", "rot_3"]), col["opacity"], sh)


def read_splat(path: str | Path) -> Gaussians:
    """Gaussians from a ``.splat`` (degree-0 colour; what its bytes hold, quantisation included)."""
    path = Path(path)
    raw = path.read_bytes()
    if len(raw) % SPLAT_RECORD.itemsize:
        raise SplatFileError(f"{path}: {len(raw)} bytes is not a whole number of 32-byte splats; not a .splat file")
    return parse_splat(raw)


def web_quantized(g: Gaussians) -> Gaussians:
    """``g`` as a web viewer holds it once loaded (from a ``.ply`` too): the degree-0 colour and the opacity in 8
    bits, the rotation in 8 bits a component; what a test or a benchmark renders to predict the viewer's picture."""
    return parse_splat(splat_bytes(g))


def parse_splat(raw: bytes) -> Gaussians:
    """Gaussians from the bytes of a ``.splat``."""
    rec = np.frombuffer(raw, SPLAT_RECORD)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], 1e-6, 1 - 1e-6)
    sh = ((rgba[:, :3] - 0.5) / SH_C0)[:, :, None]
    return Gaussians(rec["pos"].astype(np.float64), np.log(np.maximum(rec["scale"].astype(np.float64), 1e-30)),
                     (rec["rot"].astype(np.float64) - 128.0) / 128.0, np.log(alpha / (1 - alpha)), sh)


def read_splats(path: str | Path) -> Gaussians:
    """Gaussians from a ``.ply`` or ``.splat`` file, by its suffix."""
    readers = {".ply": read_ply, ".splat": read_splat}
    suffix = Path(path).suffix.lower()
    if suffix not in readers:
        raise SplatFileError(f"{path}: a splat file ends in .ply or .splat")
    return readers[suffix](path)
