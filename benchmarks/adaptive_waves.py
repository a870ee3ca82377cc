"""Adaptive waves against gabor-4 (and gabor SH against no SH on the specular scene), trained with `compare`.

    python benchmarks/adaptive_waves.py SCENE [SCENE ...] [--out runs/bench-adaptive] [--iterations 1500]
        [--num-primitives 2000] [--size 128] [--views 24] [--threshold 0.01] [--sh]
    python benchmarks/adaptive_waves.py SCENE [SCENE ...] --timing [--render-sizes 128,512] [--repeats 5]
    python benchmarks/adaptive_waves.py SCENE [SCENE ...] --train-speed

Each scene: a synthetic dataset (size x size, `views` views), then `compare gabor gabor:prune_waves=T` (or, with
--sh, `compare gabor gabor:sh_degree=3`) at a fixed primitive count without densification. Prints one table row per
run: PSNR, SSIM, kept waves, render ms, size.

--timing (after training, on a quiet machine): loads the trained models of each scene and times their test-view
renders side by side, interleaved, at each render size (the test cameras rescaled), best of `repeats`; one thread.
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
    ap.add_argument("--timing", action="store_true", help="only time the renders of runs trained earlier")
    ap.add_argument("--render-sizes", default="128,512")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--train-speed", action="store_true",
                    help="only time training iterations 200-400 of gabor-4 and of adaptive gabor pruned from the start")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.timing:
        return timing(args)
    if args.train_speed:
        return train_speed(args)
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


def timing(args) -> int:
    from splatzoo.compare import _safe
    from splatzoo.evaluate import measure_fps
    from splatzoo.runs import load_run

    for name in args.scenes:
        runs = Path(args.out) / name / "runs"
        labels = [k for k in ("gabor", _safe(f"gabor:prune_waves={args.threshold}"), _safe("gabor:sh_degree=3"))
                  if (runs / k / "model.pt").exists()]
        loaded = {k: load_run(runs / k) for k in labels}
        for size in [int(x) for x in args.render_sizes.split(",")]:
            best = {k: float("inf") for k in labels}
            for _ in range(args.repeats):
                for k in labels:  # interleaved, so drifting machine load hits every model alike
                    model, scene, _ = loaded[k]
                    cams = [v.camera.scaled(size / v.camera.width) for v in scene.test]
                    best[k] = min(best[k], 1000 / measure_fps(model, cams, scene.background, "cpu"))
            for k in labels:
                model = loaded[k][0]
                print(json.dumps({"scene": name, "model": k, "render_size": size, "render_ms": round(best[k], 2),
                                  **model.summary()}), flush=True)
    return 0


def train_speed(args) -> int:
    """Seconds for iterations 200-400 of a 400-iteration run (fixed count), gabor-4 vs adaptive with prune_from 0,
    interleaved twice, on each scene's data written by the training mode."""
    import shutil
    import tempfile

    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    variants = {"gabor": {}, "adaptive": {"prune_waves": float(args.threshold), "prune_from": 0.0}}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes:
            data = Path(args.out) / name / "data"
            for rep in range(2):
                for label, options in variants.items():
                    out = Path(tmp) / label
                    shutil.rmtree(out, ignore_errors=True)
                    cfg = TrainConfig(iterations=400, num_primitives=args.num_primitives, densify=False,
                                      log_every=50, eval_every=10 ** 9)
                    res = train(data, "gabor", options, cfg, out, progress=False, evaluate_at_end=False)
                    log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
                    t = {r["iteration"]: r["seconds"] for r in log if "seconds" in r}
                    print(json.dumps({"scene": name, "model": label, "repeat": rep, "seconds_200_400":
                                      round(t[400] - t[200], 2), **res.model.summary()}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
