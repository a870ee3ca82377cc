"""splatzoo PLY exports in third-party three.js splat viewers (Spark, GaussianSplats3D) in headless Chromium.

    python benchmarks/bench_browser_viewers.py [--out DIR] [--scene sweater] [--size 128] [--views 24]
                                               [--iterations 1000] [--surfels 2000]

Trains (once; runs are kept in --out) a 2dgs model with and without the pixel-footprint filter (`antialias`, the
training default) and a gabor model on a synthetic scene with a white backdrop, at a fixed surfel count, exports each
with `splatzoo.export.save_ply`, renders every test view in each viewer with several settings and prints the mean
PSNR of the viewer's frame against splatzoo's own render (`model.render`) and against the ground truth. Writes
--out/results.json and, per model, --out/<model>.png: the first test view as ground truth | splatzoo | Spark |
GaussianSplats3D (default settings).

Viewer settings (tests/browser/render.js passes them through):
  spark default        SparkRenderer defaults: +0.3 px^2 on the screen covariance, opacity rescaled by
                       sqrt(det / det') (Mip-Splatting's rule), radial sort
  spark blur 0.1       blurAmount 0.1: the same rule with splatzoo's anti-aliasing footprint (0.1 px^2)
  spark no blur        blurAmount 0
  spark 2DGS           enable2DGS: a splat with a zero scale (our scale_2 = -inf) is drawn as a flat quad in 3D
                       (exact perspective, no screen filter)
  gs3d default         DropInViewer defaults: +0.3 px^2 (kernel2DSize), no opacity change (3DGS's rule)
  gs3d aa              antialiased: +0.3 px^2 with the opacity rescaled (Mip-Splatting's rule)
  gs3d aa 0.1          antialiased, kernel2DSize 0.1: splatzoo's footprint
  gs3d 2D mode         splatRenderMode TwoD (2DGS ray-splat rendering; in 0.4.7 it draws every splat half a pixel
                       left of and below where it belongs, hence its low scores)
PLY variants for the viewers' default dilation (see `dilation_compensated`), rendered with the default settings:
  PLY for 3DGS rule    each surfel's screen variance at its training-camera scale less (0.3 - f) px^2 (f = 0.1, the
                       footprint, for an anti-aliased model), at least a quarter of it; opacity lowered so that
                       the splat's mass on screen stays splatzoo's: for viewers that keep the opacity (GS3D,
                       SuperSplat/PlayCanvas, the 3DGS SIBR viewer)
  PLY for Mip rule     the same shrink, opacity raised to undo a Mip-Splatting rescale (Spark); clamped to 0.99
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

MODELS = {  # label: (model, model options, antialias)
    "2dgs": ("2dgs", {}, True),
    "2dgs (no antialias)": ("2dgs", {}, False),
    "gabor": ("gabor", {}, True),
}
SETTINGS = [  # label, viewer, options, ply variant
    ("spark default", "spark", {}, "plain"),
    ("spark blur 0.1", "spark", {"blurAmount": 0.1}, "plain"),
    ("spark no blur", "spark", {"blurAmount": 0.0}, "plain"),
    ("spark z-sort", "spark", {"sortRadial": False}, "plain"),
    ("spark blur 0.1 z-sort", "spark", {"blurAmount": 0.1, "sortRadial": False}, "plain"),
    ("spark 2DGS", "spark", {"enable2DGS": True}, "plain"),
    ("spark default, PLY for 3DGS rule", "spark", {}, "3dgs"),
    ("spark default, PLY for Mip rule", "spark", {}, "mip"),
    ("gs3d default", "gs3d", {}, "plain"),
    ("gs3d aa", "gs3d", {"antialiased": True}, "plain"),
    ("gs3d aa 0.1", "gs3d", {"antialiased": True, "kernel2DSize": 0.1}, "plain"),
    ("gs3d 2D mode", "gs3d", {"splatRenderMode": 1}, "plain"),
    ("gs3d default, PLY for 3DGS rule", "gs3d", {}, "3dgs"),
    ("gs3d default, PLY for Mip rule", "gs3d", {}, "mip"),
]
VIEWER_DILATION = 0.3  # px^2 both viewers add by default (Spark blurAmount, GS3D kernel2DSize)
PIXEL_FILTER = 0.1     # px^2, splatzoo's anti-aliasing footprint (splatzoo.rasterizers.common.PIXEL_FILTER)


def training_view_scale(means: np.ndarray, axes: np.ndarray, cameras) -> tuple[np.ndarray, np.ndarray]:
    """Where each surfel was trained, as medians over `cameras`: px2 [N], its world area per pixel^2 ((depth /
    focal)^2), and fore [N,2], how much of each axis' length (axes [N,3,2], unit) survives on screen squared
    (1 - (axis . view direction)^2, at least 0.05)."""
    px2, fore = [], []
    for cam in cameras:
        w2c = cam.world_to_camera.double().numpy()
        z = means @ w2c[2, :3] + w2c[2, 3]
        f = math.sqrt(float(cam.K[0, 0]) * float(cam.K[1, 1]))
        px2.append(np.where(z > 0.05, (z / f) ** 2, np.nan))
        d = means - np.linalg.inv(w2c)[:3, 3]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        fore.append(1 - np.einsum("nk,nki->ni", d, axes) ** 2)
    return np.nanmedian(np.stack(px2), 0), np.clip(np.median(np.stack(fore), 0), 0.05, 1.0)


def dilation_compensated(src: Path, dst: Path, cameras, antialias: bool, rule: str) -> Path:
    """A copy of PLY `src` meant to look, under a viewer's default +0.3 px^2 dilation, like splatzoo's render.

    Per surfel, at its training-camera scale (`training_view_scale`): s_i, the variance of axis i on screen (px^2);
    s_i' = max(s_i - (0.3 - f), s_i / 4), f = 0.1 for an anti-aliased model (its footprint), else 0, written back
    as the scale. The opacity keeps the splat's mass (its integral on screen, o sqrt(s0 s1) in splatzoo):
    rule "3dgs" (the viewer keeps the opacity): o' = o sqrt(s0 s1 / ((s0' + 0.3)(s1' + 0.3)));
    rule "mip" (the viewer rescales it by sqrt(s0' s1' / ((s0' + 0.3)(s1' + 0.3))), as Spark does):
    o' = o sqrt(s0 s1 / (s0' s1')); clamped to 0.99.
    """
    from plyfile import PlyData, PlyElement

    from splatzoo.geometry import quat_to_rotmat

    ply = PlyData.read(str(src))
    v = ply["vertex"].data.copy()
    means = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    q = torch.from_numpy(np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64))
    axes = quat_to_rotmat(q / q.norm(dim=1, keepdim=True)).numpy()[:, :, :2]
    px2, fore = training_view_scale(means, axes, cameras)
    footprint = PIXEL_FILTER if antialias else 0.0
    s = [np.exp(2 * v[f"scale_{i}"].astype(np.float64)) / px2 * fore[:, i] for i in (0, 1)]
    new = [np.maximum(si - (VIEWER_DILATION - footprint), 0.25 * si) for si in s]
    if rule == "3dgs":
        gain = np.sqrt(s[0] * s[1] / ((new[0] + VIEWER_DILATION) * (new[1] + VIEWER_DILATION)))
    else:
        gain = np.sqrt(s[0] * s[1] / (new[0] * new[1]))
    opacity = np.clip(gain / (1 + np.exp(-v["opacity"].astype(np.float64))), 1e-6, 0.99)
    v["opacity"] = np.log(opacity / (1 - opacity)).astype(np.float32)
    for i in (0, 1):
        v[f"scale_{i}"] = (0.5 * np.log(new[i] * px2 / fore[:, i])).astype(np.float32)
    PlyData([PlyElement.describe(v, "vertex")], text=False, comments=ply.comments).write(str(dst))
    return dst


def save_strip(images, path: Path, gap: int = 2) -> None:
    """Images [H,W,3] in [0,1] side by side (ground truth, splatzoo, Spark, GaussianSplats3D) as one PNG."""
    from PIL import Image

    h, w = images[0].shape[:2]
    canvas = np.ones((h, len(images) * (w + gap) - gap, 3))
    for k, img in enumerate(images):
        canvas[:, k * (w + gap):k * (w + gap) + w] = img
    Image.fromarray(np.round(canvas * 255).astype(np.uint8)).save(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench_browser_viewers", help="folder for the dataset, runs, PLY files, results")
    ap.add_argument("--scene", default="sweater")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--surfels", type=int, default=2000)
    ap.add_argument("--models", default=",".join(MODELS), help="comma-separated labels of: " + ", ".join(MODELS))
    args = ap.parse_args(argv)

    import browser_viewers as bv
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.export import save_ply
    from splatzoo.runs import load_run, train
    from splatzoo.training import TrainConfig

    reason = bv.missing()
    if reason:
        print(reason, file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = out / "data"
    if not data.exists():
        make_synthetic_scene(args.scene, data, views=args.views, width=args.size, height=args.size,
                             background=(1, 1, 1))
    print(f"{args.scene}, {args.size}x{args.size}, {args.views} views, {args.surfels} surfels fixed, "
          f"{args.iterations} iterations, white backdrop; PSNR (dB) averaged over the test views")
    results = {}
    with bv.BrowserViewers() as browser:
        for label in args.models.split(","):
            name, options, antialias = MODELS[label]
            run = out / "runs" / label.replace(" ", "_").replace("(", "").replace(")", "")
            if not (run / "model.pt").exists():
                t = time.time()
                train(data, name, options, TrainConfig(iterations=args.iterations, backend="cpu",
                                                       num_primitives=args.surfels, densify=False,
                                                       antialias=antialias),
                      run, progress=False, evaluate_at_end=False, overwrite=True)
                print(f"trained {label} in {time.time() - t:.0f} s")
            model, scene, _ = load_run(run, "cpu")
            plys = {"plain": save_ply(model, out / f"{run.name}.ply")}
            cams = [v.camera for v in scene.train]
            for mode in ("3dgs", "mip"):
                plys[mode] = dilation_compensated(plys["plain"], out / f"{run.name}.{mode}.ply", cams, antialias, mode)
            bg = tuple(float(c) for c in model.background) if model.background is not None else (1.0, 1.0, 1.0)
            rows = {s[0]: [] for s in SETTINGS}
            own_gt, strip = [], []
            for i, view in enumerate(scene.test):
                gt = view.image_float().double().numpy()
                with torch.no_grad():
                    own = model.render(view.camera, background=torch.tensor(bg), backend="cpu").rgb.clamp(0, 1)
                own = own.double().numpy()
                own_gt.append(bv.psnr(own, gt))
                for setting, viewer, opts, variant in SETTINGS:
                    img = browser.render(plys[variant], view.camera, viewer=viewer, background=bg, options=opts)
                    rows[setting].append((bv.psnr(img, own), bv.psnr(img, gt)))
                    if i == 0 and setting in ("spark default", "gs3d default"):
                        strip += [img]
                if i == 0:
                    strip = [gt, own] + strip
            save_strip(strip, out / f"{run.name}.png")
            results[label] = {"splatzoo_vs_gt": float(np.mean(own_gt)),
                              **{k: {"vs_splatzoo": float(np.mean([a for a, _ in r])),
                                     "vs_gt": float(np.mean([b for _, b in r]))} for k, r in rows.items()}}
            print(f"\n{label} (antialias {antialias}, {model.num_primitives} surfels): splatzoo vs ground truth "
                  f"{results[label]['splatzoo_vs_gt']:.2f}")
            print("| viewer, settings | vs splatzoo | vs ground truth | minus splatzoo's |")
            print("|---|---|---|---|")
            for k in rows:
                r = results[label][k]
                print(f"| {k} | {r['vs_splatzoo']:.2f} | {r['vs_gt']:.2f} | "
                      f"{r['vs_gt'] - results[label]['splatzoo_vs_gt']:+.2f} |", flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
