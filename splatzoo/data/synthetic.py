"""Synthetic benchmark scenes with fine surface texture, modelled on the 3D Gabor splatting paper's captures.

Each scene is a set of textured triangle meshes (superellipsoids and a floor) rendered exactly by ray casting
(open3d RaycastingScene: the hit triangle and its barycentrics give the UV, the UV gives the albedo) with
4 rays per pixel (supersample=2 on an n-rooks pattern, so axis-aligned stripes meet 4 distinct sample rows and
columns), from cameras on a spiral around the object. Shading is Lambertian under two fixed world-space lights
(evaluated at the vertices and interpolated), so colour does not depend on the viewpoint (the paper switches
view-dependent colour off). Everything is deterministic for a given (name, views, width, height, seed).
Procedural textures (knit, zig-zag, plaid) are evaluated exactly at each sample; `boots` uses tinted, tiled
scikit-image photographs (brick, grass, gravel) that ship with the package and work offline.

The result is a real COLMAP dataset that `load_scene` reads:
  DATA/images/view_000.png ...   rendered RGB over a black background
  DATA/masks/view_000.png ...    coverage of the object (anti-aliased)
  DATA/sparse/0/                 PINHOLE camera, true poses, a few thousand surface points with colours and
                                 tracks (what SfM would give), or, with sfm=True, what pycolmap SfM recovers
                                 (aligned to the true frame by a similarity so mesh.ply still fits)
  DATA/mesh.ply                  ground-truth mesh in world coordinates (vertex colours = albedo)
  DATA/scene.json                description: textures, cameras (true world_to_camera), sizes, timings

Texture scale: at the default 256x256 the knit rows and plaid lines are 3-6 pixels apart, far finer than a few
thousand 2D Gaussian surfels can carry with constant colour.
"""
from __future__ import annotations

import difflib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..errors import DataError
from ..types import Camera
from .colmap import import_pycolmap, write_model
from .sfm import sfm_in_place, similarity_align
from .staging import staged_output

SUPERSAMPLE = 2   # 2x2 = 4 rays per pixel on an n-rooks pattern: 4 distinct rows and columns per pixel
POINTS = 4000
LIGHTS = ((np.array([0.35, -0.55, 0.76]), 0.6), (np.array([-0.6, 0.5, 0.3]), 0.25))
AMBIENT = 0.3


# --- textures: albedo as a function of (u, v) in world units on the surface -----------------------------------

def _frac(x):
    return x - np.floor(x)


def _knit(u, v, col=0.028, row=0.022):
    """Brightness of a stockinette knit: rows of V-shaped stitches in columns (period ~3-4 px at 256 px)."""
    vee = np.abs(2 * _frac(u / col) - 1)                       # 0 at a column centre, 1 at its edges
    stitch = 0.78 + 0.22 * np.cos(2 * np.pi * (v / row + 0.5 * vee))
    groove = 0.86 + 0.14 * np.abs(np.sin(np.pi * u / col))
    return (stitch * groove)[:, None]


def _palette(idx, colors):
    return np.asarray(colors, dtype=np.float32)[idx % len(colors)]


def sweater_texture(uv):
    u, v = uv[:, 0], uv[:, 1]
    band = np.floor(v / 0.045).astype(np.int64)                # stripes ~6 px apart
    base = _palette(band, [(0.92, 0.88, 0.78), (0.12, 0.17, 0.38), (0.92, 0.88, 0.78), (0.72, 0.14, 0.13)])
    return base * _knit(u, v)


def vest_texture(uv):
    u, v = uv[:, 0], uv[:, 1]
    zig = np.abs(2 * _frac(u / 0.09) - 1)                      # triangle wave around the body
    band = np.floor((v + 0.05 * zig) / 0.04).astype(np.int64)
    base = _palette(band, [(0.48, 0.08, 0.13), (0.62, 0.62, 0.6), (0.86, 0.66, 0.16), (0.62, 0.62, 0.6)])
    return base * _knit(u, v, col=0.025, row=0.02)


def _sett(x):
    """One thread direction of a tartan: a repeating sequence of coloured bands 0.12 units long."""
    t = _frac(x / 0.12) * 0.12
    edges = np.array([0.04, 0.048, 0.07, 0.076, 0.1, 0.106])
    idx = np.searchsorted(edges, t, side="right")
    return _palette(idx, [(0.12, 0.3, 0.18), (0.95, 0.93, 0.85), (0.1, 0.13, 0.35), (0.8, 0.12, 0.12),
                          (0.1, 0.13, 0.35), (0.95, 0.93, 0.85), (0.12, 0.3, 0.18)])


def shirt_texture(uv):
    u, v = uv[:, 0], uv[:, 1]
    plaid = 0.5 * (_sett(u) + _sett(v))
    # Fine gingham checks on top: a 0.024 period (about 3 px) light/dark alternation.
    check = (np.floor(u / 0.012) + np.floor(v / 0.012)) % 2
    return plaid * (0.82 + 0.18 * check)[:, None]


def plain_texture(uv):
    u, v = uv[:, 0], uv[:, 1]
    base = np.array([0.55, 0.38, 0.3], dtype=np.float32)
    wave = np.stack([np.sin(2 * np.pi * v / 1.6), np.cos(2 * np.pi * u / 2.2), np.sin(2 * np.pi * (u + v) / 2.8)], 1)
    return base + 0.12 * wave


class ImageTexture:
    """A grey scikit-image photograph, tinted and tiled every `tile` world units, looked up bilinearly."""

    def __init__(self, name: str, tint, tile: float):
        import skimage.data

        try:
            img = getattr(skimage.data, name)()
        except Exception as e:  # some skimage images download on first use; these three ship with it
            raise DataError(f"scikit-image texture {name!r} is unavailable offline ({e}); use brick, grass or gravel")
        img = img.astype(np.float32) / 255.0
        self.gray = img if img.ndim == 2 else img[..., :3].mean(-1)
        self.tint = np.asarray(tint, dtype=np.float32)
        self.tile = tile
        self.name = name

    def __call__(self, uv):
        h, w = self.gray.shape
        x = _frac(uv[:, 0] / self.tile) * w - 0.5
        y = _frac(uv[:, 1] / self.tile) * h - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
        # Tiling wraps around; x0 is in [-1, w-1], so one conditional add replaces a modulo.
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        x0 += w * (x0 < 0)
        y0 += h * (y0 < 0)
        x1 = x0 + 1 - w * (x0 == w - 1)
        y1 = y0 + 1 - h * (y0 == h - 1)
        g = self.gray.ravel()
        top = (1 - fx) * g[y0 * w + x0] + fx * g[y0 * w + x1]
        bottom = (1 - fx) * g[y1 * w + x0] + fx * g[y1 * w + x1]
        val = (1 - fy) * top + fy * bottom
        return (0.15 + 0.95 * val)[:, None] * self.tint


# --- geometry ---------------------------------------------------------------------------------------------

@dataclass
class Part:
    """A textured mesh piece: vertices [V,3], triangles [T,3], uv [V,2] (world units), normals [V,3]."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    texture: Callable
    texture_name: str


def _spow(x, e):
    return np.sign(x) * np.abs(x) ** e


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def superellipsoid(name, a, b, h, e1, e2, center, texture, texture_name, rot=np.eye(3), nu=160, nv=80) -> Part:
    """Closed rounded solid |x/a|^(2/e2)... with UVs in world units: u around (arc length), v along the meridian."""
    th = np.linspace(-np.pi, np.pi, nu + 1)          # seam column duplicated so u never wraps inside a triangle
    ph = np.linspace(-np.pi / 2, np.pi / 2, nv + 1)
    T, P = np.meshgrid(th, ph)                        # [nv+1, nu+1]
    cp, sp, ct, st = np.cos(P), np.sin(P), np.cos(T), np.sin(T)
    x = a * _spow(cp, e1) * _spow(ct, e2)
    y = b * _spow(cp, e1) * _spow(st, e2)
    z = h * _spow(sp, e1)
    nx = _spow(cp, 2 - e1) * _spow(ct, 2 - e2) / a
    ny = _spow(cp, 2 - e1) * _spow(st, 2 - e2) / b
    nz = _spow(sp, 2 - e1) / h
    # Texture coordinates measured as lengths so stripes keep one width: meridian arc length on the mean profile.
    r_mean = 0.5 * (a + b)
    prof = np.stack([r_mean * _spow(np.cos(ph), e1), h * _spow(np.sin(ph), e1)], 1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(prof, axis=0), axis=1))])
    arc -= arc[nv // 2]
    u = T * r_mean
    v = np.broadcast_to(arc[:, None], T.shape)
    verts = np.stack([x, y, z], -1).reshape(-1, 3) @ rot.T + np.asarray(center)
    normals = np.stack([nx, ny, nz], -1).reshape(-1, 3) @ rot.T
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # Exact poles have a zero gradient; point them along the axis.
    pole = np.linalg.norm(np.stack([nx, ny, nz], -1).reshape(-1, 3), axis=1) < 1e-9
    normals[pole] = (np.sign(z.reshape(-1))[pole, None] * rot[:, 2][None])
    idx = np.arange((nv + 1) * (nu + 1)).reshape(nv + 1, nu + 1)
    q00, q01, q10, q11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = np.concatenate([np.stack([q00, q01, q11], -1).reshape(-1, 3),
                           np.stack([q00, q11, q10], -1).reshape(-1, 3)])
    uv = np.stack([u, v], -1).reshape(-1, 2)
    return Part(name, verts, tris.astype(np.int64), uv, normals, texture, texture_name)


def floor(name, half, z, texture, texture_name, n=40) -> Part:
    g = np.linspace(-half, half, n + 1)
    X, Y = np.meshgrid(g, g)
    verts = np.stack([X, Y, np.full_like(X, z)], -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    q00, q01, q10, q11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = np.concatenate([np.stack([q00, q01, q11], -1).reshape(-1, 3), np.stack([q00, q11, q10], -1).reshape(-1, 3)])
    normals = np.tile([0.0, 0.0, 1.0], (len(verts), 1))
    return Part(name, verts, tris.astype(np.int64), verts[:, :2].copy(), normals, texture, texture_name)


def _garment(texture, texture_name, sleeves: bool) -> list[Part]:
    parts = [superellipsoid("body", 0.5, 0.3, 0.8, 0.4, 0.7, (0, 0, 0), texture, texture_name, nu=192, nv=96)]
    if sleeves:
        for side in (-1, 1):
            d = np.array([side * math.sin(math.radians(28)), 0.0, -math.cos(math.radians(28))])
            center = np.array([side * 0.5, 0.0, 0.45]) + 0.36 * d
            parts.append(superellipsoid(f"sleeve_{'left' if side < 0 else 'right'}", 0.13, 0.13, 0.4, 0.35, 1.0,
                                        center, texture, texture_name, rot=_rot("y", side * (180 - 28)),
                                        nu=96, nv=48))
    return parts


def _boots() -> list[Part]:
    # Tile sizes put about 2-5 texels on a pixel at 256x256: the photographs' finest detail sits at the pixel
    # scale, while their coarser structure (bricks, stones, blades) gives SfM consistent features.
    brick = ImageTexture("brick", (1.0, 0.58, 0.42), tile=1.0)
    grass = ImageTexture("grass", (0.5, 0.8, 0.32), tile=1.0)
    gravel = ImageTexture("gravel", (0.78, 0.72, 0.62), tile=2.2)
    parts = []
    for x0, tex, yaw in ((-0.3, brick, -12.0), (0.3, grass, 18.0)):
        R = _rot("z", yaw)
        c = np.array([x0, 0.0, 0.0])
        parts.append(superellipsoid(f"shaft_{tex.name}", 0.15, 0.15, 0.3, 0.25, 1.0, c + R @ [0, -0.06, 0.42],
                                    tex, tex.name, rot=R, nu=128, nv=64))
        parts.append(superellipsoid(f"foot_{tex.name}", 0.16, 0.3, 0.13, 0.5, 0.8, c + R @ [0, 0.08, 0.13],
                                    tex, tex.name, rot=R, nu=128, nv=64))
    parts.append(floor("floor", 1.1, 0.0, gravel, "gravel"))
    return parts


@dataclass
class SceneSpec:
    name: str
    description: str
    build: Callable[[], list[Part]]
    target: tuple[float, float, float]     # what the cameras look at
    distance: float
    elevation: tuple[float, float]         # degrees above the horizon, first to last view
    fov_deg: float = 40.0
    specular: float = 0.0                  # strength of a view-dependent Blinn-Phong highlight (0: Lambertian only)


SCENES: dict[str, SceneSpec] = {s.name: s for s in [
    SceneSpec("sweater", "rounded body with sleeves, fine horizontal knit stripes (paper: Sweat)",
              lambda: _garment(sweater_texture, "knit stripes", True), (0, 0, 0), 2.8, (-20, 55)),
    SceneSpec("vest", "sleeveless rounded body, zig-zag knit bands",
              lambda: _garment(vest_texture, "zig-zag knit", False), (0, 0, 0), 2.6, (-20, 55)),
    SceneSpec("shirt", "rounded body with sleeves, fine tartan plaid with gingham checks (paper: Shirt)",
              lambda: _garment(shirt_texture, "plaid + checks", True), (0, 0, 0), 2.8, (-20, 55)),
    SceneSpec("boots", "two boot shapes covered in brick and grass photographs on a gravel floor (paper: Boots)",
              _boots, (0, 0, 0.25), 2.9, (18, 65)),
    SceneSpec("plain", "the sweater geometry with smooth low-frequency colour (a control scene)",
              lambda: _garment(plain_texture, "smooth", True), (0, 0, 0), 2.8, (-20, 55)),
    SceneSpec("sweater-specular", "the sweater with a white view-dependent highlight (tests view-dependent colour)",
              lambda: _garment(sweater_texture, "knit stripes", True), (0, 0, 0), 2.8, (-20, 55), specular=0.6),
]}

SPECULAR_SHININESS = 12.0  # broad highlights: a few surfels wide at 128 px, so SH of low degree can follow them


def list_scenes() -> dict[str, str]:
    """Scene name -> one-line description."""
    return {n: s.description for n, s in SCENES.items()}


def get_spec(name: str) -> SceneSpec:
    if name not in SCENES:
        close = difflib.get_close_matches(name, SCENES, n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise DataError(f"unknown synthetic scene {name!r}; known scenes: {', '.join(SCENES)}.{hint} "
                        "(`splatzoo synth --list` describes them)")
    return SCENES[name]


# --- cameras ---------------------------------------------------------------------------------------------

def synthetic_cameras(name: str, views: int = 48, width: int = 256, height: int = 256, seed: int = 0) -> list[Camera]:
    """The true cameras of a synthetic scene (float64): a spiral of views around the object, looking at it.

    Azimuth steps by the golden angle and elevation rises from the spec's first to last value, so every 8th
    view (the test split) is spread around the object too. `seed` jitters distance and azimuth slightly.
    """
    spec = get_spec(name)
    if views < 2:
        raise DataError(f"views={views}: a scene needs at least 2 views")
    if width < 8 or height < 8:
        raise DataError(f"image size {width}x{height} is too small; use at least 8x8")
    rng = np.random.default_rng(seed)
    golden = math.pi * (3 - math.sqrt(5))
    target = np.asarray(spec.target, dtype=np.float64)
    az0 = rng.uniform(0, 2 * math.pi)
    cams = []
    for i in range(views):
        t = (i + 0.5) / views
        el = math.radians(spec.elevation[0] + (spec.elevation[1] - spec.elevation[0]) * t)
        az = az0 + i * golden + rng.uniform(-0.05, 0.05)
        dist = spec.distance * (1 + rng.uniform(-0.06, 0.06))
        eye = target + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        cams.append(scene_camera(spec, eye, width, height, f"view_{i:03d}.png"))
    return cams


def scene_camera(spec, eye, width: int, height: int, name: str = "") -> Camera:
    """A camera of a synthetic scene at `eye` looking at its target with its field of view (over the shorter side),
    float64; world +z shows as up in the image."""
    target = np.asarray(spec.target, dtype=np.float64)
    f = 0.5 * min(width, height) / math.tan(math.radians(spec.fov_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return Camera(torch.from_numpy(w2c), K, width, height, name)


# --- rendering -------------------------------------------------------------------------------------------

class MeshScene:
    """All parts of a scene in one open3d RaycastingScene, with per-triangle texture ids for lookup."""

    def __init__(self, parts: list[Part]):
        try:
            import open3d as o3d
        except ImportError as e:
            raise DataError(f"synthetic scenes need open3d ({e}); install it with `pip install open3d-cpu` "
                            "(Linux x86-64) or `pip install open3d`, and on Debian/Ubuntu `apt-get install "
                            "libusb-1.0-0`") from None
        self.parts = parts
        offs = np.cumsum([0] + [len(p.vertices) for p in parts])
        self.vertices = np.concatenate([p.vertices for p in parts]).astype(np.float32)
        self.triangles = np.concatenate([p.triangles + o for p, o in zip(parts, offs)]).astype(np.int64)
        self.uv = np.concatenate([p.uv for p in parts]).astype(np.float32)
        self.normals = np.concatenate([p.normals for p in parts]).astype(np.float32)
        # Parts sharing one texture are shaded in one batch: group triangles by texture, not by part.
        textures: list = []
        for p in parts:
            if not any(p.texture is t for t in textures):
                textures.append(p.texture)
        self.textures = textures
        self.tri_texture = np.concatenate([np.full(len(p.triangles), next(i for i, t in enumerate(textures)
                                                                            if t is p.texture)) for p in parts])
        # Gouraud lighting: Lambert at the vertices, interpolated; the meshes are dense (vertices ~2 px apart at
        # 256x256), so this matches per-sample lighting and saves most of the shading time.
        light = np.full(len(self.normals), AMBIENT, dtype=np.float32)
        for d, power in LIGHTS:
            light += power * np.clip(self.normals @ (d / np.linalg.norm(d)).astype(np.float32), 0, None)
        self.vertex_light = light
        self.tri_uv = self.uv[self.triangles]                 # [T,3,2]
        self.tri_light = self.vertex_light[self.triangles]    # [T,3]
        self.scene = o3d.t.geometry.RaycastingScene()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(self.vertices)
        mesh.triangle.indices = o3d.core.Tensor(self.triangles.astype(np.int32))
        self.scene.add_triangles(mesh)
        self._o3d = o3d

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        out = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs")}

    def shade(self, prim: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray | None = None,
              specular: float = 0.0) -> np.ndarray:
        """Colour [N,3] of hits given triangle ids [N] and open3d barycentrics [N,2] (weights of v1, v2).
        With `specular` > 0 and the rays' directions [N,3], a white Blinn-Phong highlight of the fixed lights is
        added: the only view-dependent term of any scene."""
        w = np.empty((len(prim), 3), dtype=np.float32)
        w[:, 1:] = bary
        w[:, 0] = 1 - bary[:, 0] - bary[:, 1]
        uv = np.einsum("nkc,nk->nc", self.tri_uv[prim], w)
        light = np.einsum("nk,nk->n", self.tri_light[prim], w)
        if len(self.textures) == 1:
            albedo = self.textures[0](uv)
        else:
            albedo = np.empty((len(prim), 3), dtype=np.float32)
            tex = self.tri_texture[prim]
            for i, t in enumerate(self.textures):
                sel = np.nonzero(tex == i)[0]
                if len(sel):
                    albedo[sel] = t(uv[sel])
        rgb = albedo * light[:, None]
        if specular > 0 and view_dirs is not None:
            n = np.einsum("nkc,nk->nc", self.normals[self.triangles[prim]], w)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            to_eye = -view_dirs / np.maximum(np.linalg.norm(view_dirs, axis=1, keepdims=True), 1e-12)
            n *= np.sign(np.sum(n * to_eye, 1, keepdims=True) + 1e-12)  # the side the ray sees
            for d, power in LIGHTS:
                h = to_eye + (d / np.linalg.norm(d)).astype(np.float32)
                h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
                rgb += (specular * power * np.clip(np.sum(n * h, 1), 0, None) ** SPECULAR_SHININESS)[:, None]
        return np.clip(rgb, 0, 1)

    def albedo_at_vertices(self) -> np.ndarray:
        out = np.zeros((len(self.vertices), 3), dtype=np.float32)
        offs = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        for p, o in zip(self.parts, offs):
            out[o:o + len(p.vertices)] = p.texture(p.uv)
        return np.clip(out, 0, 1)


def _camera_rays(cam: Camera, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixel positions (x, y) (pixel centres at +0.5); directions scaled so z_cam = 1."""
    K = cam.K.double().numpy()
    R = cam.R.double().numpy()
    xn = ((np.asarray(xs) - K[0, 2]) / K[0, 0]).astype(np.float32)[:, None]
    yn = ((np.asarray(ys) - K[1, 2]) / K[1, 1]).astype(np.float32)[:, None]
    R = R.astype(np.float32)
    dirs = xn * R[0] + yn * R[1] + R[2]               # R^T (xn, yn, 1): rows of R are the camera axes
    origins = np.broadcast_to(cam.center.double().numpy().astype(np.float32), dirs.shape)
    return origins, dirs


def render_mesh(mesh: MeshScene, cam: Camera, supersample: int = SUPERSAMPLE,
                background=(0.0, 0.0, 0.0), specular: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact render: float32 RGB [H,W,3] and coverage [H,W], averaging supersample^2 rays per pixel."""
    s = supersample
    W, H = cam.width, cam.height
    # n-rooks offsets: sample (i, j) of the s x s grid moves within its cell so that all s*s samples have
    # distinct x and distinct y (axis-aligned stripes then get s*s sample positions across them, not s).
    i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    ox = ((j * s + i + 0.5) / (s * s)).reshape(-1)
    oy = ((i * s + j + 0.5) / (s * s)).reshape(-1)
    Y, X = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    X = (X[..., None] + ox).reshape(-1)                               # [H*W*s*s]
    Y = (Y[..., None] + oy).reshape(-1)
    o, d = _camera_rays(cam, X, Y)
    hit = mesh.cast(o, d)
    ok = np.isfinite(hit["t_hit"])
    rgb = np.broadcast_to(np.asarray(background, dtype=np.float32), (len(ok), 3)).copy()
    rgb[ok] = mesh.shade(hit["primitive_ids"][ok].astype(np.int64), hit["primitive_uvs"][ok], d[ok], specular)
    rgb = rgb.reshape(H, W, s * s, 3).mean(2)
    cov = ok.astype(np.float32).reshape(H, W, s * s).mean(2)
    return rgb, cov


def sample_points(mesh: MeshScene, cams: list[Camera], n: int, rng: np.random.Generator):
    """Surface points seen by the cameras, with colours and tracks (view index, pixel xy) in every view
    that sees them unoccluded, like a sparse SfM cloud. Points seen by fewer than two views are dropped."""
    per = max(1, math.ceil(n * 1.2 / len(cams)))
    pts, cols = [], []
    for cam in cams:
        xs = rng.uniform(0, cam.width, 6 * per)      # most scenes cover a fraction of the frame: oversample
        ys = rng.uniform(0, cam.height, 6 * per)
        o, d = _camera_rays(cam, xs, ys)
        hit = mesh.cast(o, d)
        ok = np.isfinite(hit["t_hit"])
        ok &= np.cumsum(ok) <= per
        pts.append(o[ok] + d[ok] * hit["t_hit"][ok, None])
        cols.append(mesh.shade(hit["primitive_ids"][ok].astype(np.int64), hit["primitive_uvs"][ok]))
    P = np.concatenate(pts)
    C = np.concatenate(cols)
    tracks: list[list] = [[] for _ in range(len(P))]
    for vi, cam in enumerate(cams):
        w2c = cam.world_to_camera.double().numpy()
        K = cam.K.double().numpy()
        pc = P @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = K[0, 0] * pc[:, 0] / z + K[0, 2]
            y = K[1, 1] * pc[:, 1] / z + K[1, 2]
        inside = (z > 1e-6) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
        idx = np.nonzero(inside)[0]
        if len(idx) == 0:
            continue
        c = cam.center.double().numpy()
        hit = mesh.cast(np.broadcast_to(c, (len(idx), 3)), P[idx] - c)
        seen = hit["t_hit"] > 1 - 1e-4                # nothing in front of the point along the ray
        for i in idx[seen]:
            tracks[i].append((vi, np.array([x[i], y[i]])))
    keep = [i for i, t in enumerate(tracks) if len(t) >= 2][:n]
    return P[keep], C[keep], [tracks[i] for i in keep]


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    px = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    if px.ndim == 3:
        px = px[:, :, ::-1]
    if not cv2.imwrite(str(path), px):
        raise DataError(f"cannot write image {path}; check free space and permissions")


def _write_mesh(path: Path, mesh: MeshScene) -> None:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices.astype(np.float64)),
                                  o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    m.vertex_normals = o3d.utility.Vector3dVector(mesh.normals.astype(np.float64))
    m.vertex_colors = o3d.utility.Vector3dVector(mesh.albedo_at_vertices().astype(np.float64))
    if not o3d.io.write_triangle_mesh(str(path), m, write_ascii=False):
        raise DataError(f"cannot write mesh {path}; check free space and permissions")


def _progress_fn(progress) -> Callable[[str], None]:
    if callable(progress):
        return progress
    if progress:
        import sys

        return lambda msg: print(msg, file=sys.stderr, flush=True)
    return lambda msg: None


def make_synthetic_scene(name: str, out, views: int = 48, width: int = 256, height: int = 256, seed: int = 0, *,
                         sfm: bool = False, points: int = POINTS, supersample: int = SUPERSAMPLE,
                         overwrite: bool = False, progress=None, background=(0.0, 0.0, 0.0)) -> Path:
    """Render synthetic scene `name` into the COLMAP dataset folder `out` and return its path.

    background: RGB in [0,1] behind the object (an object photographed on a white sheet: (1, 1, 1)).

    sfm=True recovers poses and points with `run_sfm` on the renders instead of writing the true ones (then
    similarity-aligned to the true frame, so mesh.ply stays valid). Nothing appears at `out` until the dataset
    is complete. See the module docstring for the layout.
    """
    spec = get_spec(name)
    say = _progress_fn(progress)
    out = Path(out).expanduser()
    t0 = time.perf_counter()
    cams = synthetic_cameras(name, views, width, height, seed)
    with staged_output(out, overwrite) as tmp:
        mesh = MeshScene(spec.build())
        (tmp / "images").mkdir()
        (tmp / "masks").mkdir()
        for i, cam in enumerate(cams):
            rgb, cov = render_mesh(mesh, cam, supersample, background=background, specular=spec.specular)
            _write_png(tmp / "images" / cam.name, rgb)
            _write_png(tmp / "masks" / cam.name, cov)
            if (i + 1) % 8 == 0 or i + 1 == len(cams):
                say(f"rendered {i + 1}/{len(cams)} views of {name} ({width}x{height})")
        t_render = time.perf_counter() - t0
        info: dict = {}
        if sfm:
            say("recovering poses with SfM ...")
            try:
                res = sfm_in_place(tmp, progress=say)
            except DataError as e:
                raise DataError(f"{str(e).replace(str(tmp / 'images'), str(out / 'images'))} (SfM struggles on "
                                "repeated stripes over a black background: `boots` works; otherwise leave out "
                                "--sfm to use the true poses)") from None
            rec = res.reconstruction
            by_name = {c.name: c for c in cams}
            reg = [im for im in rec.images.values() if im.has_pose]
            if len(reg) < 3:
                raise DataError(f"SfM registered only {len(reg)} of {len(cams)} views of {name}, too few to place "
                                "in the true frame (SfM struggles on repeated stripes over a black background: "
                                "`boots` works; otherwise leave out --sfm to use the true poses)")
            est = np.array([im.projection_center() for im in reg])
            true = np.array([by_name[im.name].center.double().numpy() for im in reg])
            s, R, t = similarity_align(est, true)
            pycolmap = import_pycolmap()

            rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
            err = np.linalg.norm(np.array([im.projection_center() for im in reg]) - true, axis=1)
            rec.write_binary(str(tmp / "sparse" / "0"))
            info["sfm"] = {"registered": len(reg), "views": len(cams), "points": rec.num_points3D(),
                           "center_error_rms": float(np.sqrt((err ** 2).mean())),
                           "center_error_max": float(err.max())}
            say(f"SfM registered {len(reg)}/{len(cams)} views; camera centres within {err.max():.4f} of the truth")
        else:
            rng = np.random.default_rng(seed + 1)
            P, C, tracks = sample_points(mesh, cams, points, rng)
            write_model(tmp / "sparse" / "0", cams, [c.name for c in cams], P, C, tracks)
        _write_mesh(tmp / "mesh.ply", mesh)
        centers = np.stack([c.center.double().numpy() for c in cams])
        info = {
            "name": name, "kind": "synthetic", "description": spec.description,
            "generator": "splatzoo.data.synthetic (open3d ray casting, Lambertian, fixed world lights)",
            "views": views, "width": width, "height": height, "seed": seed, "supersample": supersample,
            "background": [float(c) for c in background], "up": [0.0, 0.0, 1.0], "target": list(spec.target),
            "fov_deg": spec.fov_deg, "mesh": "mesh.ply", "masks": "masks",
            "radius": float(np.linalg.norm(centers - centers.mean(0), axis=1).max()),
            "parts": [{"name": p.name, "texture": p.texture_name, "vertices": len(p.vertices),
                       "triangles": len(p.triangles)} for p in mesh.parts],
            "poses": "sfm" if sfm else "true",
            "cameras": [{"name": c.name, "world_to_camera": c.world_to_camera.tolist(), "K": c.K.tolist()}
                        for c in cams],
            **info,
            "seconds": round(time.perf_counter() - t0, 3), "render_seconds": round(t_render, 3),
        }
        (tmp / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    say(f"wrote {out} in {time.perf_counter() - t0:.1f} s")
    return out
