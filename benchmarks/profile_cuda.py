"""Where a cuda render spends its time: torch.profiler's CUDA kernel table for forward+backward.

    python benchmarks/profile_cuda.py [--surfels 500000] [--waves 0] [--width 1920 --height 1080]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rasterizer import make_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, default=500_000)
    ap.add_argument("--waves", default="0")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--rows", type=int, default=18)
    args = ap.parse_args(argv)
    from splatzoo.rasterizers import rasterize

    scene, cam = make_scene("sphere", args.surfels, args.width, args.height, args.waves, seed=1)
    s = scene.to("cuda").map(lambda t: t.detach().requires_grad_(True))

    def step():
        out = rasterize(s, cam, backend="cuda")
        (out.rgb.sum() + out.depth.sum() + out.normal.sum() + out.distortion.sum()).backward()

    for _ in range(3):
        step()
    torch.cuda.synchronize()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                            torch.profiler.ProfilerActivity.CUDA]) as prof:
        for _ in range(5):
            step()
        torch.cuda.synchronize()
    print(f"{args.surfels} surfels, K={args.waves}, {args.width}x{args.height}, 5 fwd+bwd steps")
    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=args.rows, max_name_column_width=60))
    return 0


if __name__ == "__main__":
    sys.exit(main())
