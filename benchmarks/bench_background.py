"""An object on a white backdrop, trained with no flag and with each explicit background.

    python benchmarks/bench_background.py [--scene plain] [--size 128] [--iterations 1500]

Renders the built-in scene over white (`splatzoo synth NAME --background white`), then trains gabor with the
`--quick` protocol (2000 surfels, fixed count) three times: no flag (auto), --background white and --background
black, and prints the test PSNR / SSIM / LPIPS of each with what auto chose.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="plain")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--iterations", type=int, default=1500)
    args = ap.parse_args(argv)
    from splatzoo.data import load_scene
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    with tempfile.TemporaryDirectory() as tmp:
        data = make_synthetic_scene(args.scene, Path(tmp) / "data", views=args.views, width=args.size,
                                    height=args.size, background=(1.0, 1.0, 1.0))
        print(f"{args.scene} over white, {args.size}x{args.size}, {args.views} views; gabor, 2000 surfels, "
              f"{args.iterations} iterations")
        print(f"auto chose: {load_scene(data).background_note}")
        print("| --background | PSNR | SSIM | LPIPS | train s |")
        print("|---|---|---|---|---|")
        for option in ("auto", "white", "black"):
            cfg = TrainConfig(iterations=args.iterations, num_primitives=2000, densify=False, backend="cpu")
            t0 = time.perf_counter()
            m = train(data, "gabor", {}, cfg, Path(tmp) / option, progress=False,
                      scene_options={"background": option}).metrics
            print(f"| {option if option != 'auto' else '(none: auto)'} | {m['psnr']:.2f} | {m['ssim']:.4f} | "
                  f"{m['lpips']:.4f} | {time.perf_counter() - t0:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
