"""Adaptive waves against gabor-4 (and gabor SH against no SH on the specular scene), trained with `compare`.

    python benchmarks/adaptive_waves.py SCENE [SCENE ...] [--out runs/bench-adaptive] [--iterations 1500]
        [--num-primitives 2000] [--size 128] [--views 24] [--threshold 0.01] [--sh]

Each scene: a synthetic dataset (size x size, `views` views), then `compare gabor gabor:prune_waves=T` (or, with
--sh, `compare gabor gabor:sh_degree=3`) at a fixed primitive count without densification. Prints one table row per
run: PSNR, SSIM, kept waves, render ms, size.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--out", default="runs/bench-adaptive")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--num-primitives", type=int, default=2000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--threshold", default="0.01")
    ap.add_argument("--sh", action="store_true", help="compare gabor with gabor:sh_degree=3 instead")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from splatzoo.compare import compare
    from splatzoo.data.synthetic import make_synthetic_scene

    models = ["gabor", "gabor:sh_degree=3"] if args.sh else ["gabor", f"gabor:prune_waves={args.threshold}"]
    for name in args.scenes:
        out = Path(args.out) / name
        data = out / "data"
        if not (data / "sparse").exists():
            make_synthetic_scene(name, data, views=args.views, width=args.size, height=args.size)
        report = compare(models, data, out, iterations=args.iterations, num_primitives=args.num_primitives,
                         densify=False, progress=False)
        for label, r in report["runs"].items():
            row = {"scene": name, "model": label, "psnr": round(r["psnr"], 3), "ssim": round(r["ssim"], 4),
                   "waves_active": r.get("waves_active"), "wave_fraction": round(r.get("wave_fraction", 1.0), 4),
                   "render_ms": round(1000 / r["fps"], 2), "size_mb": round(r["size_bytes"] / 1e6, 4),
                   "train_s": round(r["train_seconds"] or 0, 1)}
            print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
