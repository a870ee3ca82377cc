"""Anti-aliasing: models trained at one size and rendered smaller, plain against `--antialias`.

    python benchmarks/bench_antialias.py [--scenes sweater,vest] [--models gabor,2dgs] [--size 256] [--scales 0.5,0.25]

The `--quick` protocol at --size: 24 views, 2000 surfels at fixed count, 1500 iterations, seed 0. For each scene
and model, trains without and with the pixel-footprint filter and prints test PSNR at full size, and per scale the
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
    ap.add_argument("--models", default="gabor,2dgs")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--scales", default="0.5,0.25")
    args = ap.parse_args(argv)
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
            for model in args.models.split(","):
                for aa in (False, True):
                    cfg = TrainConfig(iterations=args.iterations, num_primitives=2000, densify=False, backend="cpu",
                                      antialias=aa)
                    out = Path(tmp) / f"{scene}-{model}-{aa}"
                    t0 = time.perf_counter()
                    train(data, model, {}, cfg, out, progress=False)
                    wall = time.perf_counter() - t0
                    m = evaluate_run(out, backend="cpu", scales=scales)
                    cells = "".join(f" {m['scales'][f'{s:g}']['psnr']:.2f} | "
                                    f"{m['scales'][f'{s:g}']['consistency_psnr']:.2f} |" for s in scales)
                    print(f"| {scene} | {model} | {'on' if aa else 'off'} | {m['psnr']:.2f} |{cells} {wall:.0f} |",
                          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
