"""Textured meshes: a TSDF mesh (splatzoo.mesh) with a UV atlas and a colour texture baked from the model's own
renders, written as GLB (one binary buffer, the texture embedded as PNG) or as OBJ + MTL + PNG.

A vertex-coloured TSDF mesh holds one colour per vertex, so its colour detail is capped by the voxel size (about
half a pixel of the training views, see splatzoo.mesh). A texture decouples the two: the mesh stays coarse while
the texture keeps the detail the model renders (a Gabor model's stripes are finer than any voxel).

The recipe (`texture_mesh`):
1. UV atlas: xatlas cuts the mesh into charts and packs them into one `texture_size` square image, `padding`
   texels apart (vertices on a chart boundary are duplicated: each copy has its own UV).
2. Texels -> surface: each texel centre is located in the atlas (a ray cast against the flat UV triangles with
   open3d's RaycastingScene gives the triangle and barycentrics), which gives its 3D point and normal.
3. Bake: every view renders the model once (colour over black, un-premultiplied by alpha, and the median depth).
   A texel takes a view's colour where its point projects inside the view, faces the camera (cosine > 0) and is
   not occluded: its camera depth agrees with the rendered median depth within `occlusion_tolerance`. Colours are
   sampled bilinearly from the opaque pixels only (no background bleeds in at silhouettes). The views are blended
   with weight cos^2 x (pixels per world unit)^2, raised to `sharpness`: 1 averages the views (what scores best on
   held-out views), a high power is close to picking the best view per texel (crisper, with seams).
4. Fill: surface texels no view saw take the mesh's interpolated vertex colour (the TSDF fused colour); texels
   outside every chart are filled from their neighbours, first by a few rings of dilation (so bilinear filtering
   at chart edges reads the chart's own colours) and then by a smooth pull-push fill of the rest (so coarse
   mip levels do not average in black).

The result is a `TexturedMesh`, written as GLB or OBJ by splatzoo.mesh_files (`write_textured_mesh`), atomically.

`export_textured_mesh(run, out, **options)` does it all for a run folder; options are the fields of
`TexturedMeshOptions`. open3d and xatlas are imported inside the functions that need them.
"""
from __future__ import annotations

import dataclasses
import math
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .io import say_progress as _say
from .mesh import extract_mesh, mesh_parameters
# the mesh files and their writers, used here and still imported from this module by scripts
from .mesh_files import (TexturedMesh, check_obj_companions, glb_bytes, obj_companions,  # noqa: F401
                         png_bytes, write_glb, write_obj, write_textured_mesh)
from .options import option_value
from .types import Camera

VIEW_SETS = ("train", "all")
INVALID = 0xFFFFFFFF          # open3d's RaycastingScene id for "no hit"
MIN_TEXTURE, MAX_TEXTURE = 16, 16384


def _opt(default, help: str):
    """A dataclass field with its one-line help (shown by `splatzoo export --list`)."""
    return field(default=default, metadata={"help": help})


@dataclass
class TexturedMeshOptions:
    """How a run is meshed and textured (`splatzoo export RUN --format mesh-glb:texture_size=1024`).

    texture_size: side of the square texture in texels (16-16384). The atlas fills about 60-80% of it.
    padding: texels between atlas charts (filled by dilation, so bilinear filtering and a few mip levels do not
      mix neighbouring charts).
    max_triangles: a larger mesh is first simplified to this many triangles (open3d's quadric decimation; 0: keep
      every triangle). The texture carries the colour detail, so the mesh need only carry the shape; the atlas
      takes about 0.5 ms of CPU per triangle and a texture spread over fewer triangles gets more texels each.
    voxel_size, sdf_trunc, depth_trunc, depth, alpha_threshold, keep_largest: passed to
      `splatzoo.mesh.extract_mesh` (None: its defaults from the cameras, except the voxel, see voxel_scale).
    voxel_scale: without voxel_size, the voxel is this multiple of `extract-mesh`'s default (half a pixel there,
      so about a pixel): the texture carries the colour, and a coarser TSDF averages more depth noise (fewer
      holes), gives fewer triangles to atlas and scored higher on held-out views (benchmarks/bench_mesh_texture.py:
      2 beat 1, 3 and 4).
    views: the cameras the texture is baked from: "train" (the run's training views) or "all" (training and test).
    render_scale: render the views at this multiple of their resolution for baking (2: sharper texels where the
      texture is finer than the images; the model renders detail between the training pixels).
    sharpness: power of the per-view weight cos(angle)^2 x (pixels per unit)^2 in the blend. 1 (the default) scored
      best on held-out views (the mesh is not exactly where the model's surface is, so each view's colour lands a
      little off and a blend averages that out); larger values pick the best view more exclusively (crisper
      texels, more visible seams between views).
    occlusion_tolerance: how far (world units) a texel's depth may differ from the rendered median depth and still
      count as seen; None: 3 x the mesh's median edge length (about 3 voxels).
    unlit: mark the GLB material KHR_materials_unlit (viewers show the baked colours without relighting them).
    backend: rasterizer for the renders ("auto", "reference", "cpu", "cuda").
    """

    texture_size: int = _opt(2048, "side of the square texture in texels (16-16384)")
    padding: int = _opt(4, "texels between atlas charts")
    max_triangles: int = _opt(50000, "simplify a larger mesh to this many triangles first (0: keep all)")
    voxel_size: float | None = _opt(None, "TSDF voxel in world units (default: voxel_scale x extract-mesh's)")
    voxel_scale: float = _opt(2.0, "default voxel as a multiple of extract-mesh's (half a pixel there)")
    sdf_trunc: float | None = _opt(None, "TSDF truncation in world units (default 5 voxels)")
    depth_trunc: float | None = _opt(None, "ignore depth beyond this (default 2 x the camera distance)")
    depth: str = _opt("median", "depth fused into the TSDF: median or expected")
    alpha_threshold: float = _opt(0.5, "pixels below this alpha are not fused or sampled")
    keep_largest: bool = _opt(False, "keep only the largest connected part of the mesh")
    views: str = _opt("train", "views baked from: train or all (train + test)")
    render_scale: float = _opt(1.0, "render the views at this multiple of their resolution for baking")
    sharpness: float = _opt(1.0, "power of the per-view weight (larger: closer to the best view only)")
    occlusion_tolerance: float | None = _opt(None, "depth agreement for a view to see a texel (default 3 edges)")
    unlit: bool = _opt(True, "mark the GLB material KHR_materials_unlit")
    backend: str = _opt("auto", "rasterizer for the renders: auto, reference, cpu, cuda")

    def __post_init__(self):
        self.validate()

    def validate(self) -> "TexturedMeshOptions":
        def bad(name, want):
            raise SplatzooError(f"mesh texture option {name}={getattr(self, name)!r} is invalid: {want}")

        if not isinstance(self.texture_size, int) or not MIN_TEXTURE <= self.texture_size <= MAX_TEXTURE:
            bad("texture_size", f"use a whole number of texels from {MIN_TEXTURE} to {MAX_TEXTURE}, e.g. 1024 or 2048")
        if not isinstance(self.padding, int) or not 0 <= self.padding <= self.texture_size // 8:
            bad("padding", f"use a whole number of texels from 0 to {self.texture_size // 8} (texture_size / 8)")
        if not isinstance(self.max_triangles, int) or not (self.max_triangles == 0 or self.max_triangles >= 100):
            bad("max_triangles", "use 0 (keep every triangle) or a whole number of at least 100")
        for name in ("voxel_size", "sdf_trunc", "depth_trunc", "occlusion_tolerance", "voxel_scale"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                bad(name, "use a positive number (or leave it out for the default)")
        if self.depth not in ("median", "expected"):
            bad("depth", "use median or expected")
        if not (isinstance(self.alpha_threshold, (int, float)) and 0 < self.alpha_threshold <= 1):
            bad("alpha_threshold", "use a number in (0, 1]")
        if self.views not in VIEW_SETS:
            bad("views", f"use one of {', '.join(VIEW_SETS)}")
        if not (isinstance(self.render_scale, (int, float)) and 0.25 <= self.render_scale <= 8):
            bad("render_scale", "use a number from 0.25 to 8 (1: the views' own resolution)")
        if not (isinstance(self.sharpness, (int, float)) and 0 < self.sharpness <= 64):
            bad("sharpness", "use a positive number up to 64 (1, the default: a weighted average of the views)")
        for name in ("keep_largest", "unlit"):
            if not isinstance(getattr(self, name), bool):
                bad(name, "use true or false")
        if not isinstance(self.backend, str):
            bad("backend", "use auto, reference, cpu or cuda")
        return self


def make_options(options: dict | TexturedMeshOptions | None = None, **more) -> TexturedMeshOptions:
    """TexturedMeshOptions from keyword values (strings from a command line are converted); unknown names are an
    error that lists the known ones."""
    if isinstance(options, TexturedMeshOptions):
        base = dataclasses.asdict(options)
    else:
        base = {}
        twice = [k for k in more if k in (options or {})]
        if twice:  # one value would silently win over the other
            raise SplatzooError(f"mesh texture option(s) {', '.join(twice)} given twice (in the options and as "
                                f"keywords: {', '.join(f'{options[k]!r} and {more[k]!r}' for k in twice)}); give "
                                "each once")
        more = {**(options or {}), **more}
    hints = typing.get_type_hints(TexturedMeshOptions)
    known = [f.name for f in dataclasses.fields(TexturedMeshOptions)]
    unknown = [k for k in more if k not in known]
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], known, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise SplatzooError(f"unknown mesh texture option(s) {', '.join(unknown)}{hint}; known: {', '.join(known)}")
    defaults = {f.name: f.default for f in dataclasses.fields(TexturedMeshOptions)}
    values = {**base, **{k: option_value("mesh texture", k, hints[k], v, defaults[k]) for k, v in more.items()}}
    return TexturedMeshOptions(**values).validate()


# --- atlas and texel positions ------------------------------------------------------------------------------

def uv_atlas(positions: np.ndarray, faces: np.ndarray, texture_size: int, padding: int):
    """xatlas charts packed into one texture_size square: (vmapping [V'] original vertex of each new vertex,
    faces [F,3] into the new vertices, uvs [V',2] in [0,1])."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(positions, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(texture_size)
    pack.padding = int(padding)
    pack.bilinear = True
    pack.rotate_charts = True
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:
        raise SplatzooError(f"the UV atlas did not fit into one {texture_size}x{texture_size} texture "
                            f"({atlas.atlas_count} pages); use a larger texture_size or a smaller padding")
    vmapping, indices, uvs = atlas[0]
    return (np.asarray(vmapping, dtype=np.int64), np.asarray(indices, dtype=np.int64).reshape(-1, 3),
            np.asarray(uvs, dtype=np.float32))


def texel_hits(uvs: np.ndarray, faces: np.ndarray, size: int):
    """For each texel centre of a size x size texture: the triangle that covers it (INVALID if none) and its
    barycentrics (b1, b2) (point = (1-b1-b2) v0 + b1 v1 + b2 v2). Returns (tri [size,size] uint32,
    bary [size,size,2] float32). uvs follow the glTF convention: texel (row i, column j) has centre
    ((j+0.5)/size, (i+0.5)/size)."""
    import open3d as o3d

    verts = np.concatenate([uvs, np.zeros((len(uvs), 1), np.float32)], 1).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    c = (np.arange(size, dtype=np.float32) + 0.5) / size
    v, u = np.meshgrid(c, c, indexing="ij")
    rays = np.zeros((size, size, 6), np.float32)
    rays[..., 0], rays[..., 1], rays[..., 2], rays[..., 5] = u, v, 1.0, -1.0
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    return ans["primitive_ids"].numpy().astype(np.uint32), ans["primitive_uvs"].numpy().astype(np.float32)


def _vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; zero for isolated vertices)."""
    p = positions.astype(np.float64)
    fn = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    n = np.linalg.norm(vn, axis=1, keepdims=True)
    return (vn / np.where(n > 0, n, 1)).astype(np.float32)


def _interpolate(attr: np.ndarray, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """attr [V,C] at the points (tri [M], bary [M,2])."""
    f = faces[tri]
    b1, b2 = bary[:, :1], bary[:, 1:2]
    return (1 - b1 - b2) * attr[f[:, 0]] + b1 * attr[f[:, 1]] + b2 * attr[f[:, 2]]


# --- baking --------------------------------------------------------------------------------------------------

def _erode(mask: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood lies inside `mask` (borders count as outside)."""
    m = np.pad(mask, 1, constant_values=False)
    out = np.ones_like(mask)
    H, W = mask.shape
    for dy in range(3):
        for dx in range(3):
            out &= m[dy:dy + H, dx:dx + W]
    return out


def _sample_valid(img: np.ndarray, valid: np.ndarray, x: np.ndarray, y: np.ndarray):
    """Bilinear samples of img [H,W,C] at pixel coordinates (x, y) (pixel i spans [i, i+1)) using only the
    `valid` pixels (their weights renormalised). Returns (values [M,C], weight of valid support [M])."""
    H, W = valid.shape
    fx, fy = x - 0.5, y - 0.5
    x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    tx, ty = (fx - x0).astype(np.float32), (fy - y0).astype(np.float32)
    acc = np.zeros((len(x), img.shape[2]), np.float32)
    wsum = np.zeros(len(x), np.float32)
    for dy, wy in ((0, 1 - ty), (1, ty)):
        for dx, wx in ((0, 1 - tx), (1, tx)):
            xi, yi = x0 + dx, y0 + dy
            inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
            xi, yi = np.clip(xi, 0, W - 1), np.clip(yi, 0, H - 1)
            w = wx * wy * (inside & valid[yi, xi])
            acc += w[:, None] * img[yi, xi]
            wsum += w
    return acc / np.maximum(wsum, 1e-8)[:, None], wsum


@torch.no_grad()
def _view_render(model, cam: Camera, backend: str, alpha_threshold: float):
    """(un-premultiplied colour [H,W,3], median depth [H,W] (0 where not opaque), opaque mask [H,W]) as numpy."""
    device = next(model.parameters()).device
    out = model.render(cam, background=torch.zeros(3, device=device), backend=backend)
    alpha = out.alpha.float()
    d = out.median_depth.float()
    valid = (alpha >= alpha_threshold) & torch.isfinite(d) & (d > 0)
    rgb = (out.rgb.float() / alpha.clamp_min(1e-6)[..., None]).clamp(0, 1)
    return rgb.cpu().numpy(), torch.where(valid, d, torch.zeros_like(d)).cpu().numpy(), valid.cpu().numpy()


def bake_views(points: np.ndarray, normals: np.ndarray, model, cameras: list[Camera], *, tolerance: float,
               sharpness: float, render_scale: float = 1.0, alpha_threshold: float = 0.5, backend: str = "auto",
               progress=None):
    """Colour of the surface points [M,3] (normals [M,3]) from the model's renders. Returns (colour [M,3] float32,
    total weight [M] (0: no view saw the point), views that saw each point [M] int)."""
    from .rasterizers import resolve_backend

    say = _say(progress)
    device = next(model.parameters()).device
    backend = resolve_backend(backend, device)
    M = len(points)
    acc = np.zeros((M, 3), np.float64)
    wsum = np.zeros(M, np.float64)
    seen = np.zeros(M, np.int32)
    # a common scale keeps the weights (pixels per unit, squared, to a power) in float range
    scale = None
    pts64 = points.astype(np.float64)
    step = max(1, len(cameras) // 10)
    for i, cam in enumerate(cameras):
        if render_scale != 1.0:
            cam = cam.scaled(render_scale)
        rgb, depth, valid = _view_render(model, cam, backend, alpha_threshold)
        R = cam.R.double().cpu().numpy()
        t = cam.t.double().cpu().numpy()
        K = cam.K.double().cpu().numpy()
        Xc = pts64 @ R.T + t
        z = Xc[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        x = K[0, 0] * Xc[:, 0] / zs + K[0, 1] * Xc[:, 1] / zs + K[0, 2]
        y = K[1, 1] * Xc[:, 1] / zs + K[1, 2]
        H, W = depth.shape
        inside = front & (x >= 0) & (x < W) & (y >= 0) & (y < H)
        idx = np.nonzero(inside)[0]
        if len(idx) == 0:
            continue
        xi, yi = np.minimum(x[idx].astype(np.int64), W - 1), np.minimum(y[idx].astype(np.int64), H - 1)
        d = depth[yi, xi]
        visible = valid[yi, xi] & (np.abs(d - z[idx]) <= tolerance)
        idx, xi, yi = idx[visible], xi[visible], yi[visible]
        if len(idx) == 0:
            continue
        view = cam.center.double().cpu().numpy() - pts64[idx]
        dist = np.linalg.norm(view, axis=1)
        cos = np.einsum("ij,ij->i", view, normals[idx]) / np.maximum(dist, 1e-12)
        cos = np.abs(cos)   # either winding: the depth test already says the point faces this camera
        density = K[0, 0] / z[idx]
        if scale is None:
            scale = float(np.median(density))
        # pixels next to a silhouette or a depth edge mix two surfaces: they count a tenth
        safe = _erode(valid)[yi, xi]
        w = (np.clip(cos, 0, 1) ** 2 * (density / scale) ** 2) ** sharpness * np.where(safe, 1.0, 0.1)
        col, support = _sample_valid(rgb, valid, x[idx], y[idx])
        w = w * np.minimum(support, 1.0)
        keep = w > 0
        idx, w, col = idx[keep], w[keep], col[keep]
        acc[idx] += w[:, None] * col   # idx has no repeats: each point once per view
        wsum[idx] += w
        seen[idx] += 1
        if (i + 1) % step == 0 or i + 1 == len(cameras):
            say(f"baked {i + 1}/{len(cameras)} views ({(seen > 0).mean():.0%} of the texels seen)")
    color = (acc / np.maximum(wsum, 1e-300)[:, None]).astype(np.float32)
    return color, wsum, seen


# --- filling -------------------------------------------------------------------------------------------------

def dilate(img: np.ndarray, valid: np.ndarray, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow the valid region of img [H,W,C] by `rings` texels: each new texel is the mean of its valid
    8-neighbours. Returns (img, valid) (copies)."""
    img, valid = img.copy(), valid.copy()
    H, W = valid.shape
    for _ in range(rings):
        if valid.all():
            break
        pi = np.pad(img * valid[..., None], ((1, 1), (1, 1), (0, 0)))
        pv = np.pad(valid.astype(np.float32), 1)
        s = np.zeros_like(img)
        n = np.zeros((H, W), np.float32)
        for dy in range(3):
            for dx in range(3):
                if dy == 1 and dx == 1:
                    continue
                s += pi[dy:dy + H, dx:dx + W]
                n += pv[dy:dy + H, dx:dx + W]
        grow = ~valid & (n > 0)
        img[grow] = s[grow] / n[grow][:, None]
        valid = valid | grow
    return img, valid


def pull_push(img: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill the invalid texels of img [H,W,C] smoothly from the valid ones (a pyramid of weighted averages,
    down to one texel, then back up); valid texels are kept as they are."""
    if valid.all() or not valid.any():
        return img.copy() if valid.any() else np.zeros_like(img)
    w = valid.astype(np.float32)
    levels = [(img * w[..., None], w)]
    while max(levels[-1][1].shape) > 1:
        c, w = levels[-1]
        H, W = w.shape
        c = np.pad(c, ((0, H % 2), (0, W % 2), (0, 0)))
        w = np.pad(w, ((0, H % 2), (0, W % 2)))
        c = c[0::2, 0::2] + c[1::2, 0::2] + c[0::2, 1::2] + c[1::2, 1::2]
        w = w[0::2, 0::2] + w[1::2, 0::2] + w[0::2, 1::2] + w[1::2, 1::2]
        levels.append((c, w))
    c, w = levels[-1]
    filled = c / np.maximum(w, 1e-12)[..., None]
    for c, w in reversed(levels[:-1]):
        H, W = w.shape
        up = np.repeat(np.repeat(filled, 2, 0), 2, 1)[:H, :W]
        mean = c / np.maximum(w, 1e-12)[..., None]
        a = np.minimum(w, 1.0)[..., None]
        filled = a * mean + (1 - a) * up
    out = img.copy()
    out[~valid] = filled[~valid]
    return out


# --- the whole recipe ----------------------------------------------------------------------------------------

def texture_mesh(mesh, model, cameras: list[Camera], options: TexturedMeshOptions | dict | None = None, *,
                 progress=None) -> TexturedMesh:
    """A UV-atlased copy of `mesh` (open3d legacy TriangleMesh or TexturedMesh) with a texture baked from
    `model`'s renders seen from `cameras` (see the module docstring). info holds what the bake saw.
    A TexturedMesh that has UVs keeps them (it is baked again, e.g. with other options or views); only an open3d
    mesh is simplified to `max_triangles`."""
    opts = make_options(options)
    say = _say(progress)
    if not cameras:
        raise SplatzooError("texturing a mesh needs at least one camera to bake colours from")
    t0 = time.perf_counter()
    if opts.occlusion_tolerance is not None:
        tol = float(opts.occlusion_tolerance)
    elif isinstance(mesh, TexturedMesh) and "occlusion_tolerance" in mesh.info:
        tol = float(mesh.info["occlusion_tolerance"])   # baked before: its mesh may have been simplified since
    else:   # from the mesh as extracted (its edges are about a voxel long), before any simplification
        pos = np.asarray(mesh.positions if isinstance(mesh, TexturedMesh) else mesh.vertices, dtype=np.float64)
        tris = np.asarray(mesh.faces if isinstance(mesh, TexturedMesh) else mesh.triangles, dtype=np.int64)
        if len(tris) == 0:
            raise SplatzooError("the mesh is empty (no triangles); nothing to texture")
        tol = 3.0 * float(np.median(np.linalg.norm(pos[tris[:, [1, 2, 0]]] - pos[tris], axis=2)))
    if not isinstance(mesh, TexturedMesh) and opts.max_triangles and len(mesh.triangles) > opts.max_triangles:
        before = len(mesh.triangles)
        mesh = mesh.simplify_quadric_decimation(opts.max_triangles)
        say(f"simplified the mesh from {before} to {len(mesh.triangles)} triangles ({time.perf_counter() - t0:.1f} s)")
    base = mesh if isinstance(mesh, TexturedMesh) else TexturedMesh.from_open3d(mesh)
    base.check()
    size = opts.texture_size
    if base.uvs is not None:
        # already atlased (a textured mesh baked before): bake again into the same UVs
        positions, faces, uvs = base.positions, base.faces, base.uvs
        normals = base.normals if base.normals is not None else _vertex_normals(positions, faces)
        colors = base.colors
    else:
        t1 = time.perf_counter()
        vmap, faces, uvs = uv_atlas(base.positions, base.faces, size, opts.padding)
        positions = base.positions[vmap]
        normals = (base.normals if base.normals is not None else _vertex_normals(base.positions, base.faces))[vmap]
        colors = base.colors[vmap] if base.colors is not None else None
        say(f"UV atlas: {len(faces)} triangles, {len(positions)} vertices ({len(positions) - len(base.positions)} "
            f"duplicated on chart seams), {time.perf_counter() - t1:.1f} s")
    t1 = time.perf_counter()
    tri, bary = texel_hits(uvs, faces, size)
    covered = tri != INVALID
    t_idx = tri[covered].astype(np.int64)
    b = bary[covered]
    points = _interpolate(positions, faces, t_idx, b)
    # the face normal: a texel faces where its own triangle faces (interpolated normals tilt near creases)
    p = positions.astype(np.float64)
    fn = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    tex_normals = fn[t_idx].astype(np.float32)
    say(f"baking {covered.sum()} texels ({covered.mean():.0%} of a {size}x{size} texture) from {len(cameras)} views "
        f"(occlusion tolerance {tol:.3g}; texel lookup {time.perf_counter() - t1:.1f} s)")
    color, weight, seen = bake_views(points, tex_normals, model, cameras, tolerance=tol, sharpness=opts.sharpness,
                                     render_scale=opts.render_scale, alpha_threshold=opts.alpha_threshold,
                                     backend=opts.backend, progress=progress)
    t1 = time.perf_counter()
    unseen = weight <= 0
    if unseen.any():
        fallback = (_interpolate(colors, faces, t_idx, b) if colors is not None
                    else np.full((len(t_idx), 3), color[~unseen].mean(0) if (~unseen).any() else 0.5, np.float32))
        color[unseen] = fallback[unseen]
    img = np.zeros((size, size, 3), np.float32)
    img[covered] = color
    img, grown = dilate(img, covered, max(2, opts.padding + 1))
    img = pull_push(img, grown)
    texture = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    say(f"filled the texture around the charts ({time.perf_counter() - t1:.1f} s)")
    info = {"texture_size": size, "texels_covered": float(covered.mean()),
            "surface_seen": float(1.0 - unseen.mean()) if len(unseen) else 0.0,
            "mean_views_per_texel": float(seen[~unseen].mean()) if (~unseen).any() else 0.0,
            "vertices": int(len(positions)), "triangles": int(len(faces)), "occlusion_tolerance": tol,
            "seconds": time.perf_counter() - t0}
    say(f"texture: {info['surface_seen']:.1%} of the surface seen by a view, {info['mean_views_per_texel']:.1f} views "
        f"per texel, {info['seconds']:.1f} s")
    return TexturedMesh(positions.astype(np.float32), faces, normals=normals.astype(np.float32), uvs=uvs,
                        texture=texture, colors=colors, info=info).check()


# --- from a run ----------------------------------------------------------------------------------------------

def export_textured_mesh(source, out, *, progress=None, **options) -> Path:
    """Mesh the run folder `source` (TSDF from its training views), texture the mesh from the model's renders and
    write `out` (.glb, or .obj with .mtl and .png beside it). options: the fields of TexturedMeshOptions (strings
    from a command line are converted)."""
    from .runs import Run

    opts = make_options(options)
    out = Path(out)
    if out.suffix.lower() not in (".glb", ".obj"):
        raise SplatzooError(f"{out}: a textured mesh is written as .glb (one file) or .obj (with .mtl and .png "
                            "beside it); choose one of these suffixes")
    if out.is_dir():
        raise SplatzooError(f"cannot write the mesh to {out}: it is a folder; give a file name such as "
                            f"{out / 'mesh.glb'}")
    if out.suffix.lower() == ".obj":  # before the meshing, so that a refusal costs nothing and writes nothing
        check_obj_companions(out)
    run = Run(source)
    with run.writing("splatzoo export", out, "--out FILE.glb"):
        model, scene, _ = run.load(opts.backend)
        train = [v.camera for v in scene.train]
        voxel = opts.voxel_size
        if voxel is None:
            voxel = opts.voxel_scale * mesh_parameters(train, depth_trunc=opts.depth_trunc).voxel_size
        mesh, _, _ = extract_mesh(model, train, voxel_size=voxel, sdf_trunc=opts.sdf_trunc,
                                  depth_trunc=opts.depth_trunc, depth=opts.depth,
                                  alpha_threshold=opts.alpha_threshold, keep_largest=opts.keep_largest,
                                  backend=opts.backend, progress=progress)
        views = train if opts.views == "train" else train + [v.camera for v in scene.test]
        textured = texture_mesh(mesh, model, views, opts, progress=progress)
        write_textured_mesh(textured, out, unlit=opts.unlit)
    return out   # `splatzoo export` says where it wrote


# --- a small renderer, to look at and score a mesh -----------------------------------------------------------

def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup (clamp to edge) at uv [M,2] (glTF convention) -> [M,3] float in [0,1]."""
    H, W = texture.shape[:2]
    tex = texture.astype(np.float32) / 255.0
    x, y = uv[:, 0] * W - 0.5, uv[:, 1] * H - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    tx, ty = (x - x0)[:, None], (y - y0)[:, None]
    out = np.zeros((len(uv), 3), np.float32)
    for dy, wy in ((0, 1 - ty), (1, ty)):
        for dx, wx in ((0, 1 - tx), (1, tx)):
            out += wx * wy * tex[np.clip(y0 + dy, 0, H - 1), np.clip(x0 + dx, 0, W - 1)]
    return out


def render_mesh(mesh: TexturedMesh, camera: Camera, background=(0.0, 0.0, 0.0), *, samples: int = 1):
    """Ray-cast the mesh from `camera` (open3d's RaycastingScene) and shade it with its texture or vertex colours,
    unlit. samples: rays per pixel side (1: through the pixel centre; s: an s x s grid averaged, which
    anti-aliases edges and a texture seen from afar). Returns (rgb [H,W,3] float32, coverage mask [H,W] bool:
    at least half the pixel's rays hit)."""
    if not isinstance(samples, int) or samples < 1:
        raise SplatzooError(f"render_mesh: samples must be a whole number >= 1, got {samples!r}")
    if samples > 1:
        rgb, hit = render_mesh(mesh, camera.scaled(samples), background, samples=1)
        H, W = camera.height, camera.width
        rgb = rgb[:H * samples, :W * samples].reshape(H, samples, W, samples, 3).mean((1, 3))
        cover = hit[:H * samples, :W * samples].reshape(H, samples, W, samples).mean((1, 3))
        return rgb, cover >= 0.5
    import open3d as o3d

    mesh.check()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.positions.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    W, H = camera.width, camera.height
    ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    K = camera.K.double().cpu().numpy()
    yc = (ys - K[1, 2]) / K[1, 1]
    xc = (xs - K[0, 2] - K[0, 1] * yc) / K[0, 0]
    dirs = np.stack([xc, yc, np.ones_like(xc)], -1).reshape(-1, 3) @ camera.R.double().cpu().numpy()
    origin = np.broadcast_to(camera.center.double().cpu().numpy(), dirs.shape)
    ans = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, dirs], 1).astype(np.float32)))
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    hit = tri != INVALID
    bary = ans["primitive_uvs"].numpy()[hit]
    rgb = np.broadcast_to(np.asarray(background, np.float32), (H * W, 3)).copy()
    if mesh.texture is not None:
        rgb[hit] = sample_texture(mesh.texture, _interpolate(mesh.uvs, mesh.faces, tri[hit], bary))
    elif mesh.colors is not None:
        rgb[hit] = np.clip(_interpolate(mesh.colors, mesh.faces, tri[hit], bary), 0, 1)
    else:
        rgb[hit] = 0.8
    return rgb.reshape(H, W, 3), hit.reshape(H, W)
