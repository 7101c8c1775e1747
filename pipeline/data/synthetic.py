"""The generated default scene: a ray-cast, textured, shaded object written in the Blender layout.

Independent of the splatting renderer: rays are intersected analytically with boxes, two-sided
quads, spheres and thin vertical cylinders; surfaces are textured with the sample images that
scikit-image ships and lit by a directional light plus ambient; pixels are 3x3 supersampled.

Built so that view choice matters (world +z is up, the object sits around the origin):
- the +x side is rich (photo texture, a colour-wheel sphere, thin antennas with a flag), the
  other sides are plainer, so a 120-degree sector differs from the rest;
- an open-top cup whose textured floor is visible only from high elevations (a concavity);
- thin parts (antennas 0.02 units thick);
- a panel of fine text in a slot between two fins on the -y side, visible from few directions.
Captures: 100 train + 200 test views on the upper hemisphere (distance 4, white background when
read), like the NeRF synthetic scenes.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from pipeline.bounds import INT, bounded, require_bounds

CAMERA_ANGLE_X = 0.6911112070083618  # the Blender scenes' field of view
RADIUS = 4.0
LIGHT = torch.nn.functional.normalize(torch.tensor([0.6, 0.25, 0.75]), dim=0)
SUPERSAMPLE = 3
VERSION = 1


def _textures() -> list[Tensor]:
    """Texture images [h, w, 3] in [0, 1], from scikit-image's bundled samples."""
    import skimage.data as sk

    def rgb(a, tint=(1.0, 1.0, 1.0)):
        a = np.asarray(a, dtype=np.float32) / 255.0
        if a.ndim == 2:
            a = a[..., None] * np.asarray(tint, dtype=np.float32)
        return torch.from_numpy(np.ascontiguousarray(a[..., :3]))

    return [
        rgb(sk.astronaut()),                      # 0 rich +x face
        rgb(sk.coffee()),                         # 1 +y face
        rgb(sk.brick(), (0.85, 0.55, 0.45)),      # 2 -x face
        rgb(sk.grass(), (0.45, 0.8, 0.4)),        # 3 -y face
        rgb(sk.checkerboard(), (0.9, 0.9, 0.6)),  # 4 top
        rgb(sk.gravel(), (0.6, 0.6, 0.7)),        # 5 plinth
        rgb(sk.immunohistochemistry()),           # 6 cup walls
        rgb(sk.chelsea()),                        # 7 cup floor
        rgb(sk.colorwheel()),                     # 8 sphere
        rgb(sk.rocket()),                         # 9 flag
        rgb(sk.text(), (0.2, 0.2, 0.9)),          # 10 fine text panel
        torch.tensor([[[0.8, 0.15, 0.1]]]),      # 11 plain red (antennas)
        torch.tensor([[[0.3, 0.3, 0.35]]]),      # 12 plain grey (fins)
    ]


@dataclass
class Hit:
    t: Tensor       # [R] distance (inf where missed)
    normal: Tensor  # [R, 3]
    uv: Tensor      # [R, 2] in [0, 1]
    tex: Tensor     # [R] texture index


def _miss(n: int) -> Hit:
    return Hit(torch.full((n,), math.inf), torch.zeros(n, 3), torch.zeros(n, 2),
               torch.zeros(n, dtype=torch.long))


def _box(o, d, lo, hi, face_tex) -> Hit:
    """Axis-aligned box; face_tex: texture per face in order (-x, +x, -y, +y, -z, +z)."""
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    tmin, tmax = torch.minimum(t0, t1), torch.maximum(t0, t1)
    t_near, axis = tmin.max(dim=1)
    t_far = tmax.min(dim=1).values
    ok = (t_near < t_far) & (t_near > 1e-6)
    sign_pos = d.gather(1, axis[:, None])[:, 0] < 0  # entering through the + face
    normal = torch.zeros_like(o)
    normal.scatter_(1, axis[:, None], torch.where(sign_pos, 1.0, -1.0)[:, None])
    p = o + t_near[:, None] * d
    rel = (p - lo) / (hi - lo)
    u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
    uv = torch.stack([rel.gather(1, u_axis[:, None])[:, 0], rel.gather(1, v_axis[:, None])[:, 0]], 1)
    # keep images upright on the side faces: v follows -z
    side = axis != 2
    uv = torch.where(side[:, None], torch.stack([rel.gather(1, torch.where(axis == 0, 1, 0)[:, None])[:, 0],
                                                  1 - rel[:, 2]], 1), uv)
    tex = torch.as_tensor(face_tex)[axis * 2 + sign_pos.long()]
    return Hit(torch.where(ok, t_near, torch.full_like(t_near, math.inf)), normal, uv.clamp(0, 1), tex)


def _quad(o, d, p0, e1, e2, tex) -> Hit:
    """Two-sided parallelogram p0 + a e1 + b e2, a, b in [0, 1]."""
    n = torch.nn.functional.normalize(torch.cross(e1, e2, dim=0), dim=0)
    denom = d @ n
    safe = torch.where(denom.abs() < 1e-12, torch.full_like(denom, 1e-12), denom)
    t = ((p0 - o) @ n) / safe
    p = o + t[:, None] * d - p0
    a, b = p @ e1 / (e1 @ e1), p @ e2 / (e2 @ e2)
    ok = (t > 1e-6) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
    normal = n.expand_as(o) * torch.where(denom > 0, -1.0, 1.0)[:, None]
    return Hit(torch.where(ok, t, torch.full_like(t, math.inf)), normal,
               torch.stack([a, 1 - b], 1).clamp(0, 1), torch.full_like(t, tex, dtype=torch.long))


def _sphere(o, d, center, radius, tex) -> Hit:
    oc = o - center
    b = (oc * d).sum(1)
    c = (oc * oc).sum(1) - radius * radius
    disc = b * b - c
    t = -b - torch.sqrt(disc.clamp_min(0))
    ok = (disc > 0) & (t > 1e-6)
    n = torch.nn.functional.normalize(o + t[:, None] * d - center, dim=1)
    uv = torch.stack([torch.atan2(n[:, 1], n[:, 0]) / (2 * math.pi) + 0.5,
                      torch.acos(n[:, 2].clamp(-1, 1)) / math.pi], 1)
    return Hit(torch.where(ok, t, torch.full_like(t, math.inf)), n, uv, torch.full_like(t, tex, dtype=torch.long))


def _cylinder(o, d, x, y, radius, z0, z1, tex) -> Hit:
    """Vertical cylinder side (thin parts)."""
    ox, oy = o[:, 0] - x, o[:, 1] - y
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = ox * d[:, 0] + oy * d[:, 1]
    c = ox * ox + oy * oy - radius * radius
    disc = b * b - a * c
    t = (-b - torch.sqrt(disc.clamp_min(0))) / a.clamp_min(1e-12)
    z = o[:, 2] + t * d[:, 2]
    ok = (disc > 0) & (t > 1e-6) & (z >= z0) & (z <= z1)
    p = o + t[:, None] * d
    n = torch.nn.functional.normalize(torch.stack([p[:, 0] - x, p[:, 1] - y, torch.zeros_like(t)], 1), dim=1)
    uv = torch.stack([torch.atan2(n[:, 1], n[:, 0]) / (2 * math.pi) + 0.5, (z1 - z) / (z1 - z0)], 1)
    return Hit(torch.where(ok, t, torch.full_like(t, math.inf)), n, uv.clamp(0, 1),
               torch.full_like(t, tex, dtype=torch.long))


def _v(*xs) -> Tensor:
    return torch.tensor(xs, dtype=torch.float32)


# The scene: each primitive with the group it belongs to. Every group lies inside its box (with a
# margin), so a ray that misses a group's box misses all of the group's primitives.
PRIMITIVES: list[tuple[str, Callable[[Tensor, Tensor], Hit]]] = [
    ("body", lambda o, d: _box(o, d, _v(-0.9, -0.9, -0.75), _v(0.9, 0.9, -0.55), [5, 5, 5, 5, 5, 5])),  # plinth
    ("body", lambda o, d: _box(o, d, _v(-0.6, -0.6, -0.55), _v(0.6, 0.6, 0.15), [2, 0, 3, 1, 4, 4])),   # main block
    ("antennas", lambda o, d: _sphere(o, d, _v(0.35, 0.3, 0.4), 0.22, 8)),
    ("antennas", lambda o, d: _cylinder(o, d, 0.42, -0.38, 0.02, 0.15, 0.95, 11)),
    ("antennas", lambda o, d: _cylinder(o, d, 0.25, -0.45, 0.02, 0.15, 0.75, 11)),
    ("antennas", lambda o, d: _cylinder(o, d, 0.5, -0.1, 0.015, 0.15, 0.65, 11)),
    ("antennas", lambda o, d: _quad(o, d, _v(0.42, -0.38, 0.95), _v(0.0, 0.3, 0.0), _v(0.0, 0.0, -0.18), 9)),  # flag
    # open-top cup: four walls and a floor (the concavity)
    ("cup", lambda o, d: _quad(o, d, _v(-0.5, -0.3, 0.6), _v(0.5, 0.0, 0.0), _v(0.0, 0.0, -0.45), 6)),
    ("cup", lambda o, d: _quad(o, d, _v(-0.5, 0.3, 0.6), _v(0.5, 0.0, 0.0), _v(0.0, 0.0, -0.45), 6)),
    ("cup", lambda o, d: _quad(o, d, _v(-0.5, -0.3, 0.6), _v(0.0, 0.6, 0.0), _v(0.0, 0.0, -0.45), 6)),
    ("cup", lambda o, d: _quad(o, d, _v(0.0, -0.3, 0.6), _v(0.0, 0.6, 0.0), _v(0.0, 0.0, -0.45), 6)),
    ("cup", lambda o, d: _quad(o, d, _v(-0.5, -0.3, 0.16), _v(0.5, 0.0, 0.0), _v(0.0, 0.6, 0.0), 7)),
    # a slot on the -y side: two fins and a fine-text panel between them
    ("slot", lambda o, d: _quad(o, d, _v(-0.25, -0.6, 0.05), _v(0.0, -0.45, 0.0), _v(0.0, 0.0, -0.5), 12)),
    ("slot", lambda o, d: _quad(o, d, _v(0.05, -0.6, 0.05), _v(0.0, -0.45, 0.0), _v(0.0, 0.0, -0.5), 12)),
    ("slot", lambda o, d: _quad(o, d, _v(-0.25, -0.605, 0.05), _v(0.3, 0.0, 0.0), _v(0.0, 0.0, -0.5), 10)),
]
GROUP_BOXES = {  # (lo, hi) of each group, with a margin of at least 0.03
    "body": ((-0.95, -0.95, -0.8), (0.95, 0.95, 0.2)),
    "antennas": ((0.08, -0.52, 0.1), (0.62, 0.57, 1.0)),   # sphere, antennas, flag (x 0.42, z <= 0.95)
    "cup": ((-0.55, -0.35, 0.1), (0.05, 0.35, 0.65)),
    "slot": ((-0.3, -1.1, -0.5), (0.1, -0.55, 0.1)),       # the fins reach y = -1.05
}


def _intersect_reference(o: Tensor, d: Tensor) -> Hit:
    """The nearest hit of each ray [R]: every primitive on every ray, stacked, then gathered
    (the slow, obvious oracle of ``_intersect``)."""
    hits = [hit(o, d) for _, hit in PRIMITIVES]
    t = torch.stack([h.t for h in hits])  # [S, R]
    best = t.argmin(0)
    rows = torch.arange(o.shape[0])
    pick = lambda name: torch.stack([getattr(h, name) for h in hits])[best, rows]  # noqa: E731
    return Hit(t[best, rows], pick("normal"), pick("uv"), pick("tex"))


def _intersect(o: Tensor, d: Tensor) -> Hit:
    """``_intersect_reference``'s result: each primitive is intersected only with the rays that
    enter its group's box (the others miss it: t = inf, as the reference computes), and each ray's
    surface is copied from its nearest primitive instead of stacking all of them. Per-ray
    arithmetic on a subset is the same arithmetic, and the argmin runs over the same [S, R] times
    (ties resolved the same way): the images are identical (tested)."""
    out = _miss(o.shape[0])
    t = torch.full((len(PRIMITIVES), o.shape[0]), math.inf)  # [S, R]
    hits: dict[int, tuple[Tensor, Hit]] = {}
    for group, (lo, hi) in GROUP_BOXES.items():
        rows = (torch.isfinite(_box(o, d, _v(*lo), _v(*hi), [0] * 6).t) | _starts_inside(o, lo, hi)).nonzero()[:, 0]
        if not len(rows):
            continue
        for s, (name, hit) in enumerate(PRIMITIVES):
            if name == group:
                hits[s] = (rows, hit(o[rows], d[rows]))
                t[s, rows] = hits[s][1].t
    best = t.argmin(0)
    out.t = t.gather(0, best[None])[0]
    for s, (rows, h) in hits.items():
        mine = best[rows] == s
        at = rows[mine]
        out.normal[at], out.uv[at], out.tex[at] = h.normal[mine], h.uv[mine], h.tex[mine]
    return out


def _starts_inside(o: Tensor, lo, hi) -> Tensor:
    return ((o >= _v(*lo)) & (o <= _v(*hi))).all(1)


def _shade(hit: Hit, d: Tensor, textures: list[Tensor]) -> tuple[Tensor, Tensor]:
    """RGB [R, 3] and coverage [R] of the hits (nearest-texel lookup; supersampling smooths)."""
    rgb = torch.zeros(hit.t.shape[0], 3)
    for i, tex in enumerate(textures):
        sel = (hit.tex == i) & torch.isfinite(hit.t)
        if not bool(sel.any()):
            continue
        h, w = tex.shape[:2]
        uv = hit.uv[sel]
        px = (uv[:, 0] * (w - 1)).round().long()
        py = (uv[:, 1] * (h - 1)).round().long()
        rgb[sel] = tex[py, px]
    normal = torch.where(((hit.normal * d).sum(1) > 0)[:, None], -hit.normal, hit.normal)
    light = 0.35 + 0.65 * (normal @ LIGHT).clamp_min(0)
    return (rgb * light[:, None]).clamp(0, 1), torch.isfinite(hit.t).float()


def sample_directions(count: int, seed: int, min_elev_deg: float = 5.0, max_elev_deg: float = 70.0) -> Tensor:
    """``count`` unit directions on the upper hemisphere band, uniform in area, [count, 3]."""
    gen = torch.Generator().manual_seed(seed)
    az = torch.rand(count, generator=gen, dtype=torch.float64) * 2 * math.pi
    lo, hi = math.sin(math.radians(min_elev_deg)), math.sin(math.radians(max_elev_deg))
    z = lo + (hi - lo) * torch.rand(count, generator=gen, dtype=torch.float64)
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(az), r * torch.sin(az), z], 1)


def c2w_opengl(eye: Tensor) -> Tensor:
    """Camera-to-world [4, 4] in the Blender/OpenGL convention, looking at the origin, z up."""
    back = torch.nn.functional.normalize(eye, dim=0)  # camera +z points away from the target
    right = torch.nn.functional.normalize(torch.cross(torch.tensor([0, 0, 1.0], dtype=eye.dtype), back, dim=0), dim=0)
    up = torch.cross(back, right, dim=0)
    m = torch.eye(4, dtype=eye.dtype)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def render_view(c2w: Tensor, size: int, textures: list[Tensor]) -> np.ndarray:
    """RGBA uint8 [size, size, 4] of the scene seen by an OpenGL camera-to-world matrix."""
    s = SUPERSAMPLE
    focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    k = torch.arange(size * s, dtype=torch.float32) / s + 0.5 / s  # sub-pixel centres
    v, u = torch.meshgrid(k, k, indexing="ij")
    dirs_cam = torch.stack([(u - size / 2) / focal, -(v - size / 2) / focal, -torch.ones_like(u)], -1)
    rot = c2w[:3, :3].float()
    d = torch.nn.functional.normalize(dirs_cam.reshape(-1, 3) @ rot.T, dim=1)
    o = c2w[:3, 3].float().expand_as(d)
    hit = _intersect(o, d)
    rgb, cov = _shade(hit, d, textures)
    rgba = torch.cat([rgb * cov[:, None], cov[:, None]], 1).reshape(size, s, size, s, 4).mean((1, 3))
    rgb_straight = rgba[..., :3] / rgba[..., 3:].clamp_min(1e-6)  # PNG stores straight alpha
    out = torch.cat([rgb_straight.clamp(0, 1), rgba[..., 3:]], -1)
    return (out.numpy() * 255 + 0.5).astype(np.uint8)


def depth_truth(cameras) -> Tensor:
    """The generated scene's true depth [C, H, W] (camera z of the nearest surface, OpenCV cameras,
    pixel centres at +0.5; inf where a ray meets nothing), by the same ray casting that renders it."""
    out = []
    for k in range(len(cameras)):
        vm, kk = cameras.viewmats[k].double(), cameras.Ks[k].double()
        w, h = int(cameras.width), int(cameras.height)
        v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                              indexing="ij")
        cam = torch.stack([(u - kk[0, 2]) / kk[0, 0], (v - kk[1, 2]) / kk[1, 1], torch.ones_like(u)], -1)  # z = 1
        c2w = torch.linalg.inv(vm)
        d = cam.reshape(-1, 3) @ c2w[:3, :3].T                      # [HW, 3], camera z component 1
        norm = d.norm(dim=1, keepdim=True)
        hit = _intersect(c2w[:3, 3].float().expand(len(d), 3), (d / norm).float())
        out.append((hit.t.double() / norm[:, 0]).reshape(h, w))    # t along the unit ray -> camera z
    return torch.stack(out)


def at_fraction(done: int, total: int, parts: int) -> bool:
    """True when ``done`` of ``total`` views completes one of ``parts`` equal shares (and at the
    end): how often a caller of ``generate`` says how far it is."""
    return done == total or done * parts // total > (done - 1) * parts // total


# Below this many rays in all, the views are rendered in this process (a worker pool's start-up,
# about a second per worker, would cost more than it saves).
POOL_MIN_RAYS = 20 * 64 * 64 * SUPERSAMPLE ** 2


@dataclass(frozen=True)
class GeneratedScene:
    """What ``generate`` makes, declared (a dataset's ``generate`` section)."""

    seed: int = bounded(0, INT, ge=0)
    size: int = bounded(100, INT, ge=8, le=4096)     # square images, pixels
    n_train: int = bounded(100, INT, ge=1, le=100_000)
    n_test: int = bounded(200, INT, ge=1, le=100_000)

    def __post_init__(self) -> None:
        require_bounds(self)


def generate(out: str | Path, seed: int = 0, size: int = 100, n_train: int = 100,
             n_test: int = 200, progress: Callable[[str, int, int], None] | None = None,
             workers: int | None = None) -> Path:
    """Write the scene in the Blender layout under ``out``; returns the folder. ``progress(split,
    done, total)`` hears each written view (the caller decides how often to say so). ``workers``:
    processes rendering views in parallel (default: one per CPU for a scene of more than
    ``POOL_MIN_RAYS`` rays, else 1); the images do not depend on it."""
    GeneratedScene(seed, size, n_train, n_test)  # their declared bounds
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    final = Path(out)
    # written beside the target, then renamed into place: a reader (or a second sweep generating
    # the same scene at the same moment) never sees a half-written scene
    out = final.parent / f".{final.name}.partial-{os.getpid()}"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    splits = [("train", n_train, seed * 2 + 1), ("test", n_test, seed * 2 + 2)]
    if workers is None:
        rays = (n_train + n_test) * (size * SUPERSAMPLE) ** 2
        workers = (os.cpu_count() or 1) if rays >= POOL_MIN_RAYS else 1
    with _view_renderer(workers) as render_views:
        for split, count, split_seed in splits:
            (out / split).mkdir(parents=True, exist_ok=True)
            poses = [c2w_opengl(direction * RADIUS) for direction in sample_directions(count, split_seed)]
            chunks = [poses[i:i + VIEWS_PER_TASK] for i in range(0, count, VIEWS_PER_TASK)]
            done = 0
            for chunk in render_views(chunks, size):
                for image in chunk:
                    Image.fromarray(image, "RGBA").save(out / split / f"r_{done}.png")
                    done += 1
                    if progress is not None:
                        progress(split, done, count)
            frames = [{"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()}
                      for i, c2w in enumerate(poses)]
            with open(out / f"transforms_{split}.json", "w") as f:
                json.dump({"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}, f, indent=1)
    with open(out / "scene.json", "w") as f:
        json.dump({"generator": "pipeline.data.synthetic", "version": VERSION, "seed": seed,
                   "size": size, "rich_side_azimuth_deg": 0.0, "up": [0, 0, 1]}, f, indent=1)
    move_into_place(out, final)
    return final


SCENE_FILES = ("scene.json", "transforms_train.json", "transforms_test.json")


def move_into_place(written: Path, final: Path) -> None:
    """Rename the written scene to ``final``. If ``final`` already holds the same scene (another
    process generated it meanwhile: the scene is a function of its settings) the copy is dropped;
    a different scene or anything else there is replaced."""
    try:
        os.rename(written, final)  # atomic; fails when final is a non-empty folder
        return
    except OSError:
        if all((final / name).is_file() and (final / name).read_bytes() == (written / name).read_bytes()
               for name in SCENE_FILES):
            shutil.rmtree(written)
            return
    shutil.rmtree(final)
    os.rename(written, final)


VIEWS_PER_TASK = 5


@contextmanager
def _view_renderer(workers: int):
    """A function chunks of poses -> chunks of images, in order: here, or on a spawned process
    pool (spawn, not fork: forking a process whose torch threads have started can hang)."""
    if workers == 1:
        textures = _textures()
        yield lambda chunks, size: ([render_view(c2w, size, textures) for c2w in chunk] for chunk in chunks)
        return
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        yield lambda chunks, size: pool.map(_render_chunk, chunks, [size] * len(chunks))


_WORKER_TEXTURES: list[Tensor] = []


def _render_chunk(poses: list[Tensor], size: int) -> list[np.ndarray]:
    """A pool worker's task: one thread, the textures read once per process."""
    torch.set_num_threads(1)
    if not _WORKER_TEXTURES:
        _WORKER_TEXTURES.extend(_textures())
    return [render_view(c2w, size, _WORKER_TEXTURES) for c2w in poses]
