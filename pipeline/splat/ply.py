"""Standard 3DGS files: written by gsplat's exporter, the INRIA PLY read back as ``Gaussians``.

The INRIA PLY (what every 3DGS viewer reads) stores the raw parameters as float32 vertex
properties: x, y, z; f_dc_0..2 (SH DC per channel); f_rest_* (the higher SH coefficients,
channel-major: all of red's, then green's, then blue's); opacity (the logit); scale_0..2 (log
scales); rot_0..3 (the quaternion, w first). ``ply_compressed`` (SuperSplat) and ``splat``
(antimatter15) are lossy viewer formats: written, not read back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.splat.gaussians import Gaussians, num_sh_bases

FORMATS = ("ply", "ply_compressed", "splat")
SUFFIX = {"ply": ".ply", "ply_compressed": ".compressed.ply", "splat": ".splat"}


def export_bytes(gaussians: Gaussians, fmt: str = "ply") -> bytes:
    """The model in ``fmt`` (gsplat's exporter); rows with a non-finite value are dropped by it."""
    if fmt not in FORMATS:
        raise ValueError(f"export format must be one of {FORMATS}, got {fmt!r}")
    from gsplat.exporter import export_splats
    g = gaussians.detach().to(device="cpu", dtype=torch.float32)
    return export_splats(g.means, g.log_scales, g.quats, g.logit_opacities, g.sh0, g.shN, format=fmt)


def save(gaussians: Gaussians, path: str | Path, fmt: str = "ply") -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(export_bytes(gaussians, fmt))
    return path


def _header(data: bytes, path: Path) -> tuple[int, list[tuple[str, str]], int]:
    """(vertex count, [(type, name)] of the vertex element, byte offset of the body)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary little-endian PLY is read")
    count, props, element = None, [], None
    for line in lines:
        parts = line.split()
        if parts[:1] == ["element"]:
            element = parts[1]
            if element == "chunk":
                raise ValueError(f"{path}: a compressed PLY (chunk element) is a viewer format and "
                                 "cannot be read back; export 'ply'")
            if element == "vertex":
                count = int(parts[2])
            elif count is not None:
                raise ValueError(f"{path}: a '{element}' element follows the vertices: a compressed "
                                 "PLY is a viewer format and cannot be read back; export 'ply'")
        elif parts[:1] == ["property"] and element == "vertex":
            if parts[1] != "float":
                raise ValueError(f"{path}: vertex property {parts[-1]} is {parts[1]}, expected float")
            props.append((parts[1], parts[2]))
    if count is None:
        raise ValueError(f"{path}: no vertex element")
    return count, props, end + len(b"end_header\n")


def load(path: str | Path) -> Gaussians:
    """Read an INRIA 3DGS PLY into float32 ``Gaussians`` (CPU)."""
    path = Path(path)
    data = path.read_bytes()
    count, props, start = _header(data, path)
    names = [n for _, n in props]
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in required if n not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    k = len(rest) // 3
    if len(rest) % 3 or num_sh_bases(int(round((k + 1) ** 0.5)) - 1) != k + 1:
        raise ValueError(f"{path}: {len(rest)} f_rest properties is not 3 x (a square - 1)")
    size = 4 * len(names) * count
    if len(data) - start < size:
        raise ValueError(f"{path}: truncated ({len(data) - start} bytes of vertex data, {size} needed)")
    table = np.frombuffer(data, dtype="<f4", count=len(names) * count, offset=start).reshape(count, len(names))
    col = {n: i for i, n in enumerate(names)}

    def cols(keys):
        return torch.from_numpy(table[:, [col[c] for c in keys]].astype(np.float32))
    shn = cols(rest).reshape(count, 3, k).transpose(1, 2).contiguous() if k else torch.zeros(count, 0, 3)
    g = Gaussians(means=cols(["x", "y", "z"]), log_scales=cols(["scale_0", "scale_1", "scale_2"]),
                  quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]), logit_opacities=cols(["opacity"])[:, 0],
                  sh0=cols(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :], shN=shn)
    g.validate()
    return g
