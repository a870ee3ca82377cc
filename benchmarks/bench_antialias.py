"""Anti-aliasing: models trained at one size and rendered smaller, plain against `--antialias`.

    python benchmarks/bench_antialias.py [--scenes sweater,vest] [--models gabor,2dgs] [--size 256] [--scales 0.5,0.25]
                                         [--modes off,on,downscale] [--random-downscale 0.5]

The `--quick` protocol at --size: 24 views, 2000 surfels at fixed count, 1500 iterations, seed 0. For each scene
and model, trains without and with the pixel-footprint filter (--modes: off, on, and "downscale": on, with
--random-downscale of the training views rendered at 1/2 or 1/4 size) and prints test PSNR at full size, and per scale the
PSNR of the small render against the area-averaged ground truth and against the area average of the model's own
full-size render (`splatzoo eval RUN --scale ...`), plus the training wall time.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="sweater,vest")
    ap.add_argument("--models", default="gabor,2dgs", help="comma-separated, each as `splatzoo compare` takes it, e.g. "
                                                          "gabor:n_waves=8,wave_l1=0,2dgs")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--scales", default="0.5,0.25")
    ap.add_argument("--modes", default="off,on", help="off, on, downscale (comma-separated)")
    ap.add_argument("--random-downscale", type=float, default=0.5, help="the fraction for the downscale mode")
    args = ap.parse_args(argv)
    from splatzoo.compare import parse_model_list
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.evaluate import parse_scales
    from splatzoo.runs import evaluate_run, train
    from splatzoo.training import TrainConfig

    scales = parse_scales(args.scales)
    print(f"{args.size}x{args.size}, 24 views, 2000 surfels fixed, {args.iterations} iterations")
    cols = "".join(f" {s:g}: vs GT | {s:g}: vs own full |" for s in scales)
    print(f"| scene | model | antialias | full PSNR |{cols} train s |")
    print("|---|---|---|---|" + "---|---|" * len(scales) + "---|")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            data = make_synthetic_scene(scene, Path(tmp) / scene, views=24, width=args.size, height=args.size)
            for index, choice in enumerate(parse_model_list(args.models)):
                for mode in args.modes.split(","):
                    if mode not in ("off", "on", "downscale"):
                        raise SystemExit(f"--modes: off, on or downscale, got {mode!r}")
                    cfg = TrainConfig(iterations=args.iterations, num_primitives=2000, densify=False, backend="cpu",
                                      antialias=mode != "off",
                                      random_downscale=args.random_downscale if mode == "downscale" else 0.0)
                    out = Path(tmp) / f"{scene}-{index}-{mode}"
                    t0 = time.perf_counter()
                    train(data, choice.model, choice.options, cfg, out, progress=False)
                    wall = time.perf_counter() - t0
                    m = evaluate_run(out, backend="cpu", scales=scales)
                    cells = "".join(f" {m['scales'][f'{s:g}']['psnr']:.2f} | "
                                    f"{m['scales'][f'{s:g}']['consistency_psnr']:.2f} |" for s in scales)
                    label = f"on, {cfg.random_downscale:g} downscaled" if mode == "downscale" else mode
                    print(f"| {scene} | {choice.label} | {label} | {m['psnr']:.2f} |{cells} {wall:.0f} |",
                          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
