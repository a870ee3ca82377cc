"""gabor against 2DGS at equal model size, across model sizes: the first model gets each primitive count and sets
the byte budget with its trained size; every other model gets as many primitives as fit in that budget.

    python benchmarks/bench_equal_bytes.py [--scenes sweater,vest,shirt,boots] [--size 256] [--counts 250,500,2000]
        [--models 2dgs,gabor]

With an adaptive gabor first (`--models gabor-adaptive,2dgs`) the budget is what that model kept after
pruning its waves. The `--quick` protocol otherwise: 24 views, fixed count, 1500 iterations, seed 0. Each row shows
the image pixels per primitive of the first model (one view): the paper's scenes have about 460 (4.2k-4.5k
primitives on 1920x1080 photographs), the `--quick` protocol 8 at 128 px and 33 at 256 px.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="sweater,vest,shirt,boots")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--counts", default="250,500,2000", help="primitive counts of the first model")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--models", default="2dgs,gabor", help="models, as `splatzoo compare` takes them; the first sets "
                                                           "the budget")
    args = ap.parse_args(argv)
    from splatzoo.compare import bytes_per_primitive, parse_model_list
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    first, *others = parse_model_list(args.models)
    print(f"{args.size}x{args.size}, 24 views, fixed count, {args.iterations} iterations")
    print("| scene | pixels / primitive (first) | model | primitives | bytes | PSNR | SSIM | LPIPS | PSNR - first |")
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            data = make_synthetic_scene(scene, Path(tmp) / scene, views=24, width=args.size, height=args.size)
            for count in (int(c) for c in args.counts.split(",")):
                rows, budget = [], None
                for choice in [first, *others]:
                    n = count if budget is None else max(1, budget // bytes_per_primitive(choice))
                    cfg = TrainConfig(iterations=args.iterations, num_primitives=n, densify=False, backend="cpu")
                    result = train(data, choice.model, choice.options, cfg,
                                   Path(tmp) / f"{scene}-{count}-{choice.label}", progress=False)
                    size = result.model.size_bytes()
                    budget = size if budget is None else budget
                    rows.append((choice.label, n, size, result.metrics))
                ref = rows[0][3]
                for label, n, size, m in rows:
                    print(f"| {scene} | {args.size ** 2 / count:.0f} | {label} | {n} | {size:,} | {m['psnr']:.2f} | "
                          f"{m['ssim']:.4f} | {m['lpips']:.4f} | {m['psnr'] - ref['psnr']:+.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
