"""Mesh extraction from a trained model: render depth and colour from the training cameras, fuse them into a
truncated signed distance field (TSDF) and take its zero level set with marching cubes (the 2DGS recipe).

open3d is imported inside the functions that need it, so `import splatzoo` never loads it. The fusion uses the
tensor `open3d.t.geometry.VoxelBlockGrid`: open3d 0.20's legacy ScalableTSDFVolume integrates nothing.

Default parameters (`mesh_parameters`), from the training cameras:
- radius: the distance from the nearest camera centre to the point the cameras look at (the least-squares
  meeting point of their optical axes), as the 2DGS extractor's bounding sphere;
- depth_trunc = 2 x radius: depth beyond it is ignored, which keeps an object at the centre and drops far
  background (2DGS's default);
- voxel_size = max(depth_trunc / 1024, half a pixel's footprint at the distance of the look-at point). 2DGS uses
  depth_trunc / 1024, which for its ~1000-pixel images is finer than a pixel at the object. Our synthetic scenes
  are often 64-256 pixels wide: there a 1/1024 voxel is 2-8 times finer than what the depth maps resolve, so the
  TSDF follows per-pixel rendering noise and tears (measured at 96 px: 1/3 pixel voxels lost 15% of the
  surface), while whole-pixel voxels make sdf_trunc so wide that silhouettes bulge (mean error doubled);
- sdf_trunc = 5 x voxel_size (2DGS's default): wide enough to average a few pixels' depth noise, narrow
  enough that the two sides of a thin part (a sleeve) do not erase each other.
Pixels whose rendered alpha is below `alpha_threshold` (0.5) are left out: their depth is a weighted average
over a mostly transparent ray (or, for the median, undefined), which would fuse as floaters.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from .errors import SplatzooError
from .geometry import look_at_point
from .io import say_progress as _say
from .mesh_files import check_mesh_target, write_mesh
from .types import Camera

DEPTH_KINDS = ("median", "expected")
MESH_RESOLUTION = 1024        # 2DGS: voxel = depth_trunc / 1024
SDF_TRUNC_VOXELS = 5.0        # 2DGS: sdf_trunc = 5 voxels
DEPTH_TRUNC_RADII = 2.0       # 2DGS: depth_trunc = 2 x radius
ALPHA_THRESHOLD = 0.5
WEIGHT_THRESHOLD = 3.0        # open3d's default: a voxel must be seen by 3 views to be meshed ...
FEW_VIEWS = 24                # ... or by 2 when there are fewer views than this
BLOCK_RESOLUTION = 8          # voxels per block side: small blocks waste less memory around thin surfaces
PIXEL_FRACTION = 0.5          # default voxel: at least half a pixel's footprint at the object


@dataclass
class MeshParameters:
    """Resolved TSDF settings (world units) and the camera bounds they came from."""

    voxel_size: float
    sdf_trunc: float
    depth_trunc: float
    center: tuple[float, float, float]   # the point the cameras look at
    radius: float                        # nearest camera distance to `center`


@dataclass
class MeshStats:
    """What the fusion saw: used for the progress summary and to say why a mesh came out empty."""

    views: int = 0
    pixels: int = 0
    opaque_pixels: int = 0          # alpha >= threshold
    fused_pixels: int = 0           # opaque, finite and within depth_trunc
    nearest_opaque_depth: float = math.inf
    vertices: int = 0
    triangles: int = 0
    seconds: float = 0.0


def mesh_parameters(cameras: list[Camera], *, voxel_size: float | None = None, sdf_trunc: float | None = None,
                    depth_trunc: float | None = None) -> MeshParameters:
    """The defaults described in the module docstring; any value given explicitly is kept."""
    if not cameras:
        raise SplatzooError("mesh extraction needs at least one camera; the run's scene has no training views")
    center = look_at_point(cameras)
    dists = torch.stack([(c.center.double() - center).norm() for c in cameras])
    radius = float(dists.min())
    if not math.isfinite(radius) or radius <= 1e-9:
        radius = float(dists.max()) if float(dists.max()) > 1e-9 else 1.0
    for name, v in (("voxel_size", voxel_size), ("sdf_trunc", sdf_trunc), ("depth_trunc", depth_trunc)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise SplatzooError(f"--{name.replace('_', '-')} must be a positive number, got {v}")
    if depth_trunc is None:
        depth_trunc = DEPTH_TRUNC_RADII * radius
    if voxel_size is None:
        # one pixel's footprint at the look-at distance (median over cameras), see the module docstring
        footprint = float(np.median([float(d) / float(c.K[0, 0]) for d, c in zip(dists, cameras)]))
        voxel_size = max(depth_trunc / MESH_RESOLUTION, PIXEL_FRACTION * footprint)
    if sdf_trunc is None:
        sdf_trunc = SDF_TRUNC_VOXELS * voxel_size
    if sdf_trunc < voxel_size:
        raise SplatzooError(f"--sdf-trunc {sdf_trunc:g} is smaller than one voxel ({voxel_size:g}); the TSDF would "
                            f"have no band to interpolate in. Use at least 2-5 voxels")
    return MeshParameters(float(voxel_size), float(sdf_trunc), float(depth_trunc),
                          tuple(float(x) for x in center), radius)


@torch.no_grad()
def render_depth_frames(model, cameras: Iterable[Camera], *, depth: str = "median", alpha_threshold: float = ALPHA_THRESHOLD,
                        backend: str = "auto"):
    """Yield (camera, depth [H,W] float32 with 0 where masked, colour [H,W,3] float32 in [0,1], alpha [H,W])
    for each camera. Colour is un-premultiplied (rendered over black, divided by alpha)."""
    from .rasterizers import resolve_backend

    if depth not in DEPTH_KINDS:
        raise SplatzooError(f"--depth must be one of {', '.join(DEPTH_KINDS)}, got {depth!r}")
    device = next(model.parameters()).device
    backend = resolve_backend(backend, device)
    bg = torch.zeros(3, dtype=torch.float32, device=device)
    for cam in cameras:
        out = model.render(cam, background=bg, backend=backend)
        alpha = out.alpha
        d = out.median_depth if depth == "median" else out.depth
        keep = (alpha >= alpha_threshold) & torch.isfinite(d) & (d > 0)
        d = torch.where(keep, d, torch.zeros_like(d))
        rgb = (out.rgb / alpha.clamp_min(1e-6)[..., None]).clamp(0, 1)
        yield cam, d.float().cpu().numpy(), rgb.float().cpu().numpy(), alpha.float().cpu().numpy()


def fuse_depth_frames(frames, params: MeshParameters, *, weight_threshold: float | None = None,
                      alpha_threshold: float = ALPHA_THRESHOLD, progress=None, total: int | None = None):
    """TSDF-fuse (camera, depth, colour, alpha) frames; returns (open3d.geometry.TriangleMesh, MeshStats).

    The mesh is open3d's legacy TriangleMesh (vertex colours in [0,1]); it may be empty, see `extract_mesh`.
    weight_threshold: views that must have seen a voxel for it to be meshed. Default 3 (open3d's), 2 with fewer
    than 24 views (a 14-view spiral sees much of the surface only twice: 3 lost 2% more of it), never more than
    the number of views; 1 keeps surfaces seen once, but also spurious crossings at the edges of one view's band.
    """
    import open3d as o3d
    import open3d.core as o3c

    say = _say(progress)
    stats = MeshStats()
    t0 = time.perf_counter()
    # The block hash map grows as needed (checked: 100 -> 6928 blocks); its initial capacity is allocated up
    # front (block_count x 8^3 voxels x 20 bytes), so start small.
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1,), (1,), (3,)), voxel_size=params.voxel_size, block_resolution=BLOCK_RESOLUTION,
        block_count=1000, device=o3c.Device("CPU:0"))
    trunc_mult = params.sdf_trunc / params.voxel_size
    step = max(1, (total or 10) // 10)
    for i, (cam, depth, color, alpha) in enumerate(frames):
        stats.views += 1
        stats.pixels += depth.size
        opaque = alpha >= alpha_threshold
        stats.opaque_pixels += int(opaque.sum())
        valid = (depth > 0) & (depth <= params.depth_trunc)
        stats.fused_pixels += int(valid.sum())
        if (depth > 0).any():
            stats.nearest_opaque_depth = min(stats.nearest_opaque_depth, float(depth[depth > 0].min()))
        if valid.any():
            # OpenCV intrinsics as they are: open3d's integration looks up pixel floor(u), so pixel i spans
            # [i, i+1) with its centre at i + 0.5, our convention
            K = o3c.Tensor(cam.K.double().cpu().numpy())
            E = o3c.Tensor(cam.world_to_camera.double().cpu().numpy())
            d_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth, dtype=np.float32)))
            c_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color, dtype=np.float32)))
            try:
                blocks = grid.compute_unique_block_coordinates(d_img, K, E, 1.0, params.depth_trunc, trunc_mult)
            except RuntimeError:  # open3d: "No block is touched in TSDF volume": this view adds nothing
                stats.fused_pixels -= int(valid.sum())
                blocks = None
            if blocks is not None:
                grid.integrate(blocks, d_img, c_img, K, E, 1.0, params.depth_trunc, trunc_mult)
        if (i + 1) % step == 0 or (total is not None and i + 1 == total):
            say(f"fused {i + 1}/{total or '?'} views ({stats.fused_pixels} depth pixels)")
    if weight_threshold is None:
        weight_threshold = min(WEIGHT_THRESHOLD if stats.views >= FEW_VIEWS else 2.0, float(stats.views))
    if stats.fused_pixels == 0:
        mesh = o3d.geometry.TriangleMesh()
    else:
        mesh = grid.extract_triangle_mesh(weight_threshold=weight_threshold).to_legacy()
    stats.vertices, stats.triangles = len(mesh.vertices), len(mesh.triangles)
    stats.seconds = time.perf_counter() - t0
    return mesh, stats


def keep_largest_component(mesh):
    """The largest connected component (by triangle count) of an open3d legacy TriangleMesh, in place."""
    if len(mesh.triangles) == 0:
        return mesh
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels = np.asarray(labels)
    largest = int(np.argmax(np.asarray(counts)))
    mesh.remove_triangles_by_mask(labels != largest)
    mesh.remove_unreferenced_vertices()
    return mesh


def _empty_mesh_reason(stats: MeshStats, params: MeshParameters, alpha_threshold: float) -> str:
    if stats.opaque_pixels == 0:
        return (f"nothing opaque: no pixel of the {stats.views} training views reaches alpha {alpha_threshold:g}. "
                "The model is untrained or transparent; train longer, or lower --alpha-threshold")
    if stats.fused_pixels == 0:
        return (f"every opaque pixel lies beyond the depth truncation {params.depth_trunc:.4g} (the nearest is at "
                f"{stats.nearest_opaque_depth:.4g}); raise --depth-trunc")
    return (f"{stats.fused_pixels} depth pixels were fused but no surface crossed the volume (bounds): with voxel "
            f"size {params.voxel_size:.4g} and sdf_trunc {params.sdf_trunc:.4g} the views do not agree on a surface "
            "seen often enough; try a smaller --voxel-size or a larger --sdf-trunc")


def extract_mesh(model, cameras: list[Camera], *, voxel_size: float | None = None, sdf_trunc: float | None = None,
                 depth_trunc: float | None = None, depth: str = "median", alpha_threshold: float = ALPHA_THRESHOLD,
                 weight_threshold: float | None = None, keep_largest: bool = False, backend: str = "auto",
                 progress=None):
    """Fuse the model's depth seen from `cameras` into a coloured triangle mesh.

    Returns (open3d.geometry.TriangleMesh, MeshParameters, MeshStats). Raises SplatzooError saying why when the
    mesh comes out empty. depth: "median" (the surface where transmittance crosses 0.5; sharp on objects, the
    2DGS choice for bounded scenes) or "expected" (alpha-weighted mean depth; smoother, biased at silhouettes).
    """
    say = _say(progress)
    if not 0.0 < alpha_threshold <= 1.0:
        raise SplatzooError(f"--alpha-threshold must be in (0, 1], got {alpha_threshold}")
    params = mesh_parameters(cameras, voxel_size=voxel_size, sdf_trunc=sdf_trunc, depth_trunc=depth_trunc)
    say(f"TSDF: voxel {params.voxel_size:.4g}, sdf_trunc {params.sdf_trunc:.4g}, depth_trunc {params.depth_trunc:.4g} "
        f"({depth} depth, alpha >= {alpha_threshold:g}, {len(cameras)} views)")
    frames = render_depth_frames(model, cameras, depth=depth, alpha_threshold=alpha_threshold, backend=backend)
    mesh, stats = fuse_depth_frames(frames, params, weight_threshold=weight_threshold,
                                    alpha_threshold=alpha_threshold, progress=progress, total=len(cameras))
    if len(mesh.triangles) == 0:
        raise SplatzooError("the extracted mesh is empty: " + _empty_mesh_reason(stats, params, alpha_threshold))
    if keep_largest:
        before = len(mesh.triangles)
        keep_largest_component(mesh)
        stats.vertices, stats.triangles = len(mesh.vertices), len(mesh.triangles)
        say(f"kept the largest component: {stats.triangles} of {before} triangles")
    say(f"mesh: {stats.vertices} vertices, {stats.triangles} triangles ({stats.seconds:.1f} s)")
    return mesh, params, stats


def extract_mesh_from_run(run_dir, out=None, *, backend: str = "auto", progress=None, **options) -> Path:
    """Extract the mesh of a trained run (training cameras) and write it to `out` (default RUN/mesh.ply).
    `options` are those of `extract_mesh`."""
    from .runs import Run

    run = Run(run_dir)
    # refused before minutes of work; a read-only run folder is named by run.writing, with the option to use
    out = check_mesh_target(Path(out) if out is not None else run.path / "mesh.ply", writable=False)
    with run.writing("splatzoo extract-mesh", out, "--out FILE.ply"):
        check_mesh_target(out)
        model, scene, _ = run.load(backend)
        mesh, _, _ = extract_mesh(model, [v.camera for v in scene.train], backend=backend, progress=progress, **options)
        write_mesh(mesh, out)
    _say(progress)(f"wrote {out}")
    return out


# --- accuracy against a known surface (synthetic scenes) -----------------------------------------------------

def visible_surface_points(gt_mesh, cameras: list[Camera], max_points: int = 20000, seed: int = 0) -> np.ndarray:
    """Points on `gt_mesh` (open3d legacy TriangleMesh) hit by the cameras' pixel rays [M,3]: the part of the
    true surface the views can see, sampled about uniformly in image space."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(gt_mesh))
    pts = []
    for cam in cameras:
        W, H = cam.width, cam.height
        ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
        K = cam.K.double().numpy()
        dirs_c = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1).reshape(-1, 3)
        R = cam.R.double().numpy()
        dirs = dirs_c @ R                              # camera -> world: R^T d, row-wise
        origin = np.broadcast_to(cam.center.double().numpy(), dirs.shape)
        rays = o3d.core.Tensor(np.concatenate([origin, dirs], 1).astype(np.float32))
        t = scene.cast_rays(rays)["t_hit"].numpy()
        hit = np.isfinite(t)
        pts.append(origin[hit] + t[hit, None] * dirs[hit])
    pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    return pts


def _distance_to(mesh, points: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()


def mesh_accuracy(mesh, gt_mesh, cameras: list[Camera], radius: float, *, within: float = 0.02,
                  max_points: int = 20000) -> dict:
    """Compare an extracted mesh with the true one (both open3d legacy TriangleMesh).

    accuracy: mean distance from the mesh's vertices to the true surface, / radius;
    completeness: fraction of points on the true surface visible from `cameras` within `within` x radius of the
    mesh (and their mean distance / radius).
    """
    verts = np.asarray(mesh.vertices)
    if len(verts) == 0:
        raise SplatzooError("cannot score an empty mesh")
    acc = _distance_to(gt_mesh, verts)
    vis = visible_surface_points(gt_mesh, cameras, max_points=max_points)
    comp = _distance_to(mesh, vis)
    return {"radius": radius, "accuracy_mean": float(acc.mean() / radius),
            "accuracy_median": float(np.median(acc) / radius),
            "completeness_mean": float(comp.mean() / radius),
            "completeness_within": float((comp <= within * radius).mean()), "within": within,
            "vertices": int(len(verts)), "visible_points": int(len(vis))}
