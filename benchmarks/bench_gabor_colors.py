"""gabor's colour parametrisations against 2DGS at equal count on the built-in scenes: residual (the default: a 2DGS
base colour with waves around it), the paper's with the public release's start, and the paper's started as the 2DGS
surfel (init=surfel).

    python benchmarks/bench_gabor_colors.py [--scenes plain,plain-white,sweater,vest,shirt,boots] [--size 128]

The `--quick` protocol: 24 views, 2000 surfels at fixed count, 1500 iterations, seed 0. `plain-white` is the plain
scene rendered over white (trained with the background auto finds: white). Prints test PSNR / SSIM / LPIPS and the
difference of each gabor to 2DGS.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

MODELS = (("2dgs", "2dgs", {}), ("gabor residual (default)", "gabor", {"color_param": "residual"}),
          ("gabor paper", "gabor", {"color_param": "paper", "init": "paper"}),
          ("gabor paper init=surfel", "gabor", {"color_param": "paper", "init": "surfel"}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="plain,plain-white,sweater,vest,shirt,boots")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--models", default=",".join(label for label, _, _ in MODELS),
                    help="comma-separated labels of the models to train (2dgs first: the differences are to it)")
    args = ap.parse_args(argv)
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    print(f"{args.size}x{args.size}, 24 views, 2000 surfels fixed, {args.iterations} iterations")
    print("| scene | model | PSNR | SSIM | LPIPS | PSNR - 2dgs | LPIPS - 2dgs |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            name, white = scene.removesuffix("-white"), scene.endswith("-white")
            data = make_synthetic_scene(name, Path(tmp) / scene, views=24, width=args.size, height=args.size,
                                        background=(1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0))
            ref = None
            for label, model, options in [m for m in MODELS if m[0] in args.models.split(",")]:
                cfg = TrainConfig(iterations=args.iterations, num_primitives=2000, densify=False, backend="cpu")
                m = train(data, model, options, cfg, Path(tmp) / f"{scene}-{label}", progress=False).metrics
                ref = ref or m
                print(f"| {scene} | {label} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['lpips']:.4f} | "
                      f"{m['psnr'] - ref['psnr']:+.2f} | {m['lpips'] - ref['lpips']:+.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
