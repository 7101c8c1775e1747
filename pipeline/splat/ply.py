"""Standard 3DGS files: written by gsplat's exporter, the INRIA PLY read back as ``Gaussians``.

The INRIA PLY (what every 3DGS viewer reads) stores the raw parameters as float32 vertex
properties: x, y, z; f_dc_0..2 (SH DC per channel); f_rest_* (the higher SH coefficients,
channel-major: all of red's, then green's, then blue's); opacity (the logit); scale_0..2 (log
scales); rot_0..3 (the quaternion, w first). ``ply_compressed`` (SuperSplat) and ``splat``
(antimatter15) are lossy viewer formats; the ``.splat`` is read back too, as what it holds (8-bit
colour and opacity, no view-dependent SH, 8-bit rotations); ``spz`` (Niantic, through
``gsply``) is quantised but read back too. Reading PLY goes through
``plyfile`` (binary of either endianness or ASCII; extra properties such as normals or uchar
colours are ignored).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import torch

from pipeline.splat.gaussians import Gaussians, num_sh_bases

FORMATS = ("ply", "ply_compressed", "splat", "spz")
SUFFIX = {"ply": ".ply", "ply_compressed": ".compressed.ply", "splat": ".splat", "spz": ".spz"}


def export_bytes(gaussians: Gaussians, fmt: str = "ply") -> bytes:
    """The model in ``fmt``: gsplat's exporter (rows with a non-finite value are dropped by it),
    or Niantic's SPZ through ``gsply`` (quantised: about 10x smaller than the PLY)."""
    if fmt not in FORMATS:
        raise ValueError(f"export format must be one of {FORMATS}, got {fmt!r}")
    g = gaussians.detach().to(device="cpu", dtype=torch.float32)
    if fmt == "spz":
        return _spz_bytes(g)
    from gsplat.exporter import export_splats
    return export_splats(g.means, g.log_scales, g.quats, g.logit_opacities, g.sh0, g.shN, format=fmt)


def _gsdata(g: Gaussians):
    import gsply
    quats = torch.nn.functional.normalize(g.quats, dim=-1)  # SPZ stores unit quaternions
    return gsply.GSData(means=g.means.numpy(), scales=g.log_scales.numpy(), quats=quats.numpy(),
                        opacities=g.logit_opacities.numpy(), sh0=g.sh0[:, 0].numpy(), shN=g.shN.numpy(),
                        _format=gsply.create_ply_format(sh_degree=g.sh_degree))


def _spz_bytes(g: Gaussians) -> bytes:
    import tempfile

    import gsply
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.spz"
        gsply.write_spz(path, _gsdata(g))
        return path.read_bytes()


def load_spz(path: Path) -> Gaussians:
    """A Niantic SPZ file (``gsply``) as float32 ``Gaussians``."""
    import gsply
    try:
        data = gsply.read_spz(path)
    except Exception as err:  # gsply raises its own errors for a bad container
        raise ValueError(f"{path}: not a readable SPZ file ({err})") from None
    n = data.means.shape[0]
    shn = np.zeros((n, 0, 3), np.float32) if data.shN is None else np.asarray(data.shN, np.float32)
    g = Gaussians(means=torch.from_numpy(np.asarray(data.means, np.float32)),
                  log_scales=torch.from_numpy(np.asarray(data.scales, np.float32)),
                  quats=torch.from_numpy(np.asarray(data.quats, np.float32)),
                  logit_opacities=torch.from_numpy(np.asarray(data.opacities, np.float32)),
                  sh0=torch.from_numpy(np.asarray(data.sh0, np.float32))[:, None, :],
                  shN=torch.from_numpy(shn.reshape(n, -1, 3)))
    g.validate()
    return g


def written_count(data: bytes, fmt: str) -> int:
    """How many Gaussians an exported file holds (an exporter may drop rows): the PLY vertex
    count (the compressed PLY's too), 32 bytes per .splat row, the SPZ header's count."""
    if fmt == "splat":
        return len(data) // 32
    if fmt == "spz":
        import gzip
        raw = gzip.decompress(data) if data[:2] == b"\x1f\x8b" else data
        return struct.unpack_from("<I", raw, 8)[0]  # magic, version, then the point count
    head = data[:data.find(b"end_header")].decode("ascii", errors="replace")
    for line in head.splitlines():
        if line.startswith("element vertex "):
            return int(line.split()[2])
    raise ValueError("the exported PLY has no vertex element")


def save(gaussians: Gaussians, path: str | Path, fmt: str = "ply") -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(export_bytes(gaussians, fmt))
    return path


def _vertex_table(path: Path):
    """The vertex element of a PLY file (any of plyfile's encodings: binary either endianness,
    ASCII), refusing the lossy viewer formats with a message that says so."""
    from plyfile import PlyData, PlyElementParseError, PlyHeaderParseError
    try:
        data = PlyData.read(str(path))
    except PlyHeaderParseError as err:
        raise ValueError(f"{path}: not a PLY file ({err})") from None
    except (PlyElementParseError, EOFError, struct.error) as err:
        raise ValueError(f"{path}: truncated or malformed vertex data ({err})") from None
    names = [e.name for e in data.elements]
    if "chunk" in names:
        raise ValueError(f"{path}: a compressed PLY (chunk element) is a viewer format and cannot be "
                         "read back; export 'ply'")
    if "vertex" not in names:
        raise ValueError(f"{path}: no vertex element")
    if names.index("vertex") != len(names) - 1:
        following = names[names.index("vertex") + 1]
        raise ValueError(f"{path}: a '{following}' element follows the vertices: a compressed PLY is a "
                         "viewer format and cannot be read back; export 'ply'")
    return data["vertex"]


READABLE = {".ply": "INRIA 3DGS PLY", ".spz": "Niantic SPZ", ".splat": "antimatter15 .splat (lossy)"}
SPLAT_ROW = 32  # bytes: position float32 x3, scale float32 x3, RGBA uint8 x4, quaternion uint8 x4
SH_C0 = 0.28209479177387814  # the degree-0 SH basis constant: colour = 0.5 + C0 * dc


def load_splat(path: Path) -> Gaussians:
    """An antimatter15 ``.splat`` file (what ``gopre-export --format splat`` writes) as ``Gaussians``:
    positions and scales exact (float32), colour and opacity to 1/255, rotations to 1/128, and no
    view-dependent colour (SH degree 0): what the format holds."""
    data = path.read_bytes()
    if not data or len(data) % SPLAT_ROW:
        raise ValueError(f"{path}: {len(data)} bytes is not a whole number of {SPLAT_ROW}-byte .splat rows")
    rows = np.frombuffer(data, dtype=np.dtype([("position", "<f4", 3), ("scale", "<f4", 3),
                                               ("rgba", "u1", 4), ("rotation", "u1", 4)]))
    scales = rows["scale"].astype(np.float64)
    if not np.isfinite(scales).all() or (scales <= 0).any():
        raise ValueError(f"{path}: not a .splat file (non-positive or non-finite scales)")
    rgba = rows["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], 0.5 / 255, 1 - 0.5 / 255)  # 0 and 255 are the ends of a rounded range
    quats = (rows["rotation"].astype(np.float64) - 128.0) / 128.0
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(norms > 0, quats / np.maximum(norms, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    count = len(rows)

    def tensor(values):
        return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))
    g = Gaussians(means=tensor(rows["position"]), log_scales=tensor(np.log(scales)), quats=tensor(quats),
                  logit_opacities=tensor(np.log(alpha / (1 - alpha))),
                  sh0=tensor((rgba[:, :3] - 0.5) / SH_C0)[:, None, :], shN=torch.zeros(count, 0, 3))
    g.validate()
    return g


def load(path: str | Path) -> Gaussians:
    """Read a 3DGS file into float32 ``Gaussians`` (CPU): an INRIA PLY (extra vertex properties
    such as normals or uchar colours are ignored; the 3DGS ones may be float or double), an SPZ,
    or an antimatter15 ``.splat``. Any other suffix is refused naming the formats read."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file")
    if path.suffix == ".spz":
        return load_spz(path)
    if path.suffix == ".splat":
        return load_splat(path)
    if path.suffix != ".ply":
        accepted = ", ".join(f"{suffix} ({name})" for suffix, name in READABLE.items())
        raise ValueError(f"{path}: not a model file this reads; accepted: {accepted}")
    vertex = _vertex_table(path)
    names = [prop.name for prop in vertex.properties]
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in required if n not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    k = len(rest) // 3
    if len(rest) % 3 or num_sh_bases(int(round((k + 1) ** 0.5)) - 1) != k + 1:
        raise ValueError(f"{path}: {len(rest)} f_rest properties is not 3 x (a square - 1)")
    for name in required + rest:
        kind = vertex[name].dtype.kind
        if kind != "f":
            raise ValueError(f"{path}: vertex property {name} is {vertex[name].dtype}, expected float")
    count = len(vertex.data)

    def cols(keys):
        return torch.from_numpy(np.stack([np.asarray(vertex[c], dtype=np.float32) for c in keys], axis=1))
    shn = cols(rest).reshape(count, 3, k).transpose(1, 2).contiguous() if k else torch.zeros(count, 0, 3)
    g = Gaussians(means=cols(["x", "y", "z"]), log_scales=cols(["scale_0", "scale_1", "scale_2"]),
                  quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]), logit_opacities=cols(["opacity"])[:, 0],
                  sh0=cols(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :], shN=shn)
    g.validate()
    return g
