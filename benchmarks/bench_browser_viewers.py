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


def dilation_compensated(src: Path, dst: Path, cameras, rule: str) -> Path:
    """A copy of PLY `src` made for a viewer's default +0.3 px^2 dilation under `rule` ("3dgs": the viewer keeps the
    opacity; "mip": it rescales it): splatzoo.export.compensate_viewer_dilation, what `splatzoo export --format
    ply:viewer=3dgs` writes."""
    from splatzoo.export import compensate_viewer_dilation, load_ply, save_ply

    model = load_ply(src)
    compensate_viewer_dilation(model, cameras, rule)
    return save_ply(model, dst)


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
                plys[mode] = dilation_compensated(plys["plain"], out / f"{run.name}.{mode}.ply", cams, mode)
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
