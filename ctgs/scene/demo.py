"""The built-in demo scene: a small room rendered exactly, written as a COLMAP scene.

Layout (world units ~ metres, z up): a 5 x 5 floor, back/left/right walls 3 high, a box rotated on the
floor and two standing panels. Some surfaces carry real photographs bundled with scikit-image, others
are flat or smoothly shaded, so a content-aware method should spend its texels on the photos.
Cameras sit on a 120-degree arc in front of the content, all looking at it.

Output (see `make_demo_scene`): OUT/images/NNN.png, OUT/sparse/0/*.bin with the TRUE pinhole cameras
and surface-sampled coloured points, and OUT/demo_meta.json describing every surface.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from ctgs.errors import UserError
from ctgs.io import atomic, owner
from ctgs.io.images import write_image
from ctgs.scene.levels import LEVEL
from ctgs.scene.colmap_write import PinholeCamera, write_colmap_model
from ctgs.scene.raycast import Rect, render

META_NAME = "demo_meta.json"
META_VERSION = 2  # 2: SfM-like points (gradient-weighted), see sample_points
SFM_CANDIDATES = 30  # area-uniform candidates per kept point
SFM_GRADIENT_STEP = 0.03  # world units, ~1 pixel of the closest camera at 96 px width
SFM_FLOOR = 0.05  # sampling weight of textureless spots, relative to the median textured gradient
HORIZONTAL_FOV_DEG = 60.0
ARC_DEG = 120.0  # azimuth span of the camera arc
TARGET = np.array([0.0, 0.6, 0.6])  # world point every camera looks at
ARC_RADIUS = 2.7  # horizontal distance of the cameras from TARGET, world units
BACKGROUND = (0.0, 0.0, 0.0)  # rays leaving the room (rare)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _photo(name: str, tint=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A scikit-image sample photo as float [H, W, 3] in [0, 1] (grey ones tinted)."""
    # scikit-image only while the demo scene is made
    import skimage.data

    img = getattr(skimage.data, name)().astype(np.float64) / 255.0
    if img.ndim == 2:
        img = img[:, :, None] * np.asarray(tint)[None, None]
    return img[:, :, :3]


def _crop_to_aspect(img: np.ndarray, aspect: float) -> np.ndarray:
    """Centre crop [H, W, 3] to width/height == aspect, so photos are not stretched on the surface."""
    h, w = img.shape[:2]
    if w / h > aspect:
        nw = max(1, round(h * aspect))
        x0 = (w - nw) // 2
        return img[:, x0:x0 + nw]
    nh = max(1, round(w / aspect))
    y0 = (h - nh) // 2
    return img[y0:y0 + nh]


def _box_faces(prefix: str, center, half: float, yaw_deg: float, kinds: dict) -> list[Rect]:
    """Five visible faces (no bottom) of a cube of half size `half` resting on z = 0, yawed about z."""
    a = math.radians(yaw_deg)
    ex, ey, ez = np.array([math.cos(a), math.sin(a), 0.0]), np.array([-math.sin(a), math.cos(a), 0.0]), np.eye(3)[2]
    c = np.asarray(center, dtype=np.float64)
    faces = {  # name -> (centre, u, v); u x v is the outward normal
        "front": (c - half * ey, ex, ez),
        "back": (c + half * ey, -ex, ez),
        "left": (c - half * ex, -ey, ez),
        "right": (c + half * ex, ey, ez),
        "top": (c + half * ez, ex, ey),
    }
    rects = []
    for name, (fc, u, v) in faces.items():
        kind, payload = kinds[name]
        rects.append(_rect(f"{prefix}_{name}", kind, fc, u, v, (half, half), payload))
    return rects


def _rect(rid: str, kind: str, center, u, v, half, payload) -> Rect:
    if kind == "photo":
        name, tint = payload
        return Rect(rid, kind, np.asarray(center, float), _unit(u), _unit(v), half, np.zeros(3),
                    texture=_photo(name, tint), texture_name=name)
    if kind == "smooth":
        c1, c2 = payload
        return Rect(rid, kind, np.asarray(center, float), _unit(u), _unit(v), half, np.asarray(c1, float),
                    color2=np.asarray(c2, float))
    return Rect(rid, kind, np.asarray(center, float), _unit(u), _unit(v), half, np.asarray(payload, float))


def demo_surfaces() -> list[Rect]:
    """The demo room (textures at source resolution; `make_demo_scene` prefilters them)."""
    x, y, z = np.eye(3)
    rects = [
        _rect("floor", "photo", (0, 0, 0), x, y, (2.5, 2.5), ("gravel", (0.95, 0.82, 0.62))),
        _rect("back_wall", "photo", (0, 2.5, 1.5), x, z, (2.5, 1.5), ("astronaut", None)),
        _rect("left_wall", "flat", (-2.5, 0, 1.5), y, z, (2.5, 1.5), (0.50, 0.60, 0.75)),
        _rect("right_wall", "smooth", (2.5, 0, 1.5), -y, z, (2.5, 1.5), ((0.88, 0.78, 0.55), (0.55, 0.33, 0.30))),
        _rect("poster", "photo", (-1.2, 1.3, 0.9), _unit((math.cos(0.35), math.sin(0.35), 0)), z, (0.6, 0.4),
              ("rocket", None)),
        _rect("panel", "flat", (1.5, 1.2, 0.55), _unit((math.cos(-0.4), math.sin(-0.4), 0)), z, (0.4, 0.5),
              (0.85, 0.70, 0.15)),
    ]
    rects += _box_faces("box", (0.1, 0.4, 0.45), 0.45, 30.0, {
        "front": ("photo", ("chelsea", None)),
        "left": ("photo", ("coffee", None)),
        "right": ("flat", (0.78, 0.22, 0.16)),
        "back": ("flat", (0.45, 0.45, 0.45)),
        "top": ("smooth", ((0.95, 0.94, 0.88), (0.55, 0.68, 0.88))),
    })
    return rects


def _look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4, 4] world -> camera for a camera at `center` looking at `target` (x right, y down, z forward)."""
    f = _unit(target - center)
    r = _unit(np.cross(f, np.array([0.0, 0.0, 1.0])))
    d = np.cross(f, r)  # down; r x d = f keeps the frame right-handed
    R = np.stack([r, d, f])
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ center
    return viewmat


def demo_cameras(num_views: int, width: int, height: int, seed: int) -> tuple[PinholeCamera, list[np.ndarray]]:
    """Shared pinhole intrinsics and num_views viewmats on a jittered arc (deterministic for `seed`)."""
    rng = np.random.default_rng(seed + 1)
    fx = 0.5 * width / math.tan(math.radians(HORIZONTAL_FOV_DEG) / 2)
    camera = PinholeCamera(width, height, fx, fx, width / 2, height / 2)
    azimuths = np.radians(np.linspace(-ARC_DEG / 2, ARC_DEG / 2, num_views))
    azimuths = azimuths + np.radians(rng.uniform(-1.0, 1.0, num_views))
    viewmats = []
    for a in azimuths:
        height_z = 1.4 + 0.25 * math.sin(3 * a) + rng.uniform(-0.05, 0.05)
        center = TARGET + np.array([ARC_RADIUS * math.sin(a), -ARC_RADIUS * math.cos(a), 0.0])
        center[2] = height_z
        viewmats.append(_look_at(center, TARGET + rng.uniform(-0.05, 0.05, 3)))
    return camera, viewmats


def _nearest_distance(rect: Rect, centers: np.ndarray) -> float:
    """Smallest distance from any camera centre [C, 3] to the rectangle, world units."""
    rel = centers - rect.center[None]
    lx = np.clip(rel @ rect.u, -rect.half[0], rect.half[0])
    ly = np.clip(rel @ rect.v, -rect.half[1], rect.half[1])
    nearest = rect.center[None] + lx[:, None] * rect.u[None] + ly[:, None] * rect.v[None]
    return float(np.linalg.norm(centers - nearest, axis=1).min())


def _prefilter(rects: list[Rect], centers: np.ndarray, focal: float) -> None:
    """Crop photos to their surface's aspect and shrink them to ~1 texel per pixel at the closest view
    (a one-level mipmap: bilinear + supersampling alone would alias on far, minified surfaces)."""
    # scikit-image only while the demo scene is made
    from skimage.transform import resize

    for rect in rects:
        if rect.kind != "photo":
            continue
        tex = _crop_to_aspect(rect.texture, rect.half[0] / rect.half[1])
        density = focal / max(_nearest_distance(rect, centers), 1e-3)  # texels per world unit
        w = min(tex.shape[1], max(8, math.ceil(2 * rect.half[0] * density)))
        h = min(tex.shape[0], max(8, math.ceil(2 * rect.half[1] * density)))
        if (h, w) != tex.shape[:2]:
            tex = resize(tex, (h, w), anti_aliasing=True, order=1)
        rect.texture = np.clip(tex, 0.0, 1.0).astype(np.float32)


def _inside_box(p: np.ndarray, rects: list[Rect]) -> np.ndarray:
    """[P] bool: points strictly inside the demo box (floor samples hidden under it)."""
    top = next(r for r in rects if r.id == "box_top")
    half = top.half[0]
    rel = p - (top.center - np.array([0, 0, half]))[None]
    return (np.abs(rel @ top.u) < half) & (np.abs(rel @ top.v) < half) & (rel[:, 2] < half)


def sample_points(rects: list[Rect], count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` SfM-like points with their true colours: ([P,3], [P,3] uint8).

    Real SfM only triangulates where there is image texture, so flat walls get almost no points. Points are
    drawn from area-uniform candidates with probability ~ local colour gradient + a small floor (a few
    points still land on flat surfaces, as SfM finds some at their borders). Uniform points made the
    trainer start with as many primitives on flat walls as on photos, which no real scene does.
    """
    rng = np.random.default_rng(seed)
    areas = np.array([r.area for r in rects])
    per_rect = rng.multinomial(count * SFM_CANDIDATES, areas / areas.sum())
    pts, cols, grads = [], [], []
    for rect, n in zip(rects, per_rect):
        lx = rng.uniform(-rect.half[0], rect.half[0], n)
        ly = rng.uniform(-rect.half[1], rect.half[1], n)
        pts.append(rect.center[None] + lx[:, None] * rect.u[None] + ly[:, None] * rect.v[None])
        cols.append(rect.shade(lx, ly))
        grads.append(_colour_gradient(rect, lx, ly))
    p, c, g = np.concatenate(pts), np.concatenate(cols), np.concatenate(grads)
    keep = ~_inside_box(p, rects)  # floor samples hidden under the box
    p, c, g = p[keep], c[keep], g[keep]
    textured = g[g > 0]
    w = g + SFM_FLOOR * (np.median(textured) if textured.size else 1.0)
    idx = rng.choice(len(p), size=min(count, len(p)), replace=False, p=w / w.sum())
    return p[idx], np.round(np.clip(c[idx], 0, 1) * 255).astype(np.uint8)


def _colour_gradient(rect: Rect, lx: np.ndarray, ly: np.ndarray) -> np.ndarray:
    """[P] sum of |central differences| of the surface colour over SFM_GRADIENT_STEP world units (u and v)."""
    def at(x, y):
        return rect.shade(np.clip(x, -rect.half[0], rect.half[0]), np.clip(y, -rect.half[1], rect.half[1]))

    h = SFM_GRADIENT_STEP
    return (np.abs(at(lx + h, ly) - at(lx - h, ly)).sum(1) + np.abs(at(lx, ly + h) - at(lx, ly - h)).sum(1))


def _surface_meta(rect: Rect) -> dict:
    meta = {
        "id": rect.id, "kind": rect.kind,
        "center": rect.center.tolist(), "normal": rect.normal.tolist(),
        "u": rect.u.tolist(), "v": rect.v.tolist(),
        "half_extents": list(rect.half), "area": rect.area,
    }
    if rect.kind == "photo":
        meta["texture"] = rect.texture_name
        meta["texture_resolution"] = [int(rect.texture.shape[1]), int(rect.texture.shape[0])]  # [W, H]
    else:
        meta["color"] = rect.color.tolist()
        if rect.color2 is not None:
            meta["color2"] = rect.color2.tolist()
    return meta


def make_demo_scene(out_dir: str, *, num_views: int = 40, width: int = 256, height: int = 192, seed: int = 0,
                    points: int = 5000, supersample: int = 3, overwrite: bool = False) -> str:
    """Render the demo scene into out_dir (COLMAP layout); returns out_dir's absolute path.

    Idempotent: if out_dir already holds a demo scene made with the same parameters it is kept as is.
    Another demo scene in out_dir is an error unless `overwrite`; a folder of other files always is.
    """
    if num_views < 3 or width < 16 or height < 16 or points < 1 or supersample < 1:
        raise UserError(f"demo scene: need >= 3 views, >= 16x16 pixels, >= 1 point, supersample >= 1 "
                        f"(got views={num_views}, {width}x{height}, points={points}, supersample={supersample})")
    out_dir = os.path.abspath(out_dir)
    params = {"num_views": num_views, "width": width, "height": height, "seed": seed, "points": points,
              "supersample": supersample, "version": META_VERSION}
    meta_path = os.path.join(out_dir, META_NAME)
    if os.path.isfile(meta_path) and not overwrite and _read_meta(meta_path).get("params") == params:
        return out_dir  # (a damaged demo_meta.json reads as {}: not an identical scene, refused below)
    # --force replaces an earlier demo scene, never a folder of the user's (ctgs.io.owner)
    owner.check_ours(out_dir, DEMO_KIND, "an earlier demo scene", legacy=_legacy_demo, also=_level)
    if os.path.isdir(out_dir) and os.listdir(out_dir) and not overwrite:
        if os.path.isfile(meta_path) and not _read_meta(meta_path):
            raise UserError(f"{meta_path}: damaged, so this folder cannot be checked to be the same demo scene; "
                            f"remove {out_dir} or pass --force")
        raise UserError(f"{out_dir}: holds a demo scene made with other options; pass --force to replace it, or "
                        "choose another folder")

    rects = demo_surfaces()
    camera, viewmats = demo_cameras(num_views, width, height, seed)
    centers = np.stack([-v[:3, :3].T @ v[:3, 3] for v in viewmats])  # [C, 3]
    _prefilter(rects, centers, camera.fx)
    pts, cols = sample_points(rects, points, seed)

    with owner.owned_dir(out_dir, DEMO_KIND) as tmp:
        names = [f"{i:03d}.png" for i in range(num_views)]
        for name, viewmat in zip(names, viewmats):
            image = render(rects, viewmat, camera.fx, camera.fy, camera.cx, camera.cy, width, height,
                           ss=supersample, background=BACKGROUND)
            write_image(os.path.join(tmp, "images", name), image)
        write_colmap_model(os.path.join(tmp, "sparse", "0"), camera, names, viewmats, pts, cols)
        meta = {
            "params": params,
            "intrinsics": {"width": width, "height": height, "fx": camera.fx, "fy": camera.fy,
                           "cx": camera.cx, "cy": camera.cy},
            "units": "world units ~ metres; z up",
            "target": TARGET.tolist(),
            "background": list(BACKGROUND),
            "surfaces": [_surface_meta(r) for r in rects],
            "cameras": [{"name": n, "center": c.tolist()} for n, c in zip(names, centers)],
        }
        atomic.write_json(os.path.join(tmp, META_NAME), meta, indent=1)
    return out_dir


DEMO_KIND = "demo-scene"


def _level(name: str) -> bool:
    """images_N: a level training made in the scene (ctgs.scene.levels)."""
    return bool(LEVEL.match(name))


def _legacy_demo(names: list[str]) -> bool:
    """A demo scene written before folders were marked: its names only."""
    return META_NAME in names and all(n in ("images", "sparse", META_NAME) or _level(n) for n in names)


def _read_meta(path: str) -> dict:
    """demo_meta.json as a dict, {} when it cannot be parsed (a damaged file)."""
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except ValueError:
        return {}
    return meta if isinstance(meta, dict) else {}
