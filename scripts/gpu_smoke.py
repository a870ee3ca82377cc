"""Training smoke test on the GPU: a short gabor run on the cuda backend, interrupted and resumed.

    python scripts/gpu_smoke.py DATA OUT [--iterations 600] [--backend cuda] [--num-primitives 4000] [--min-gain 3]

Checks that training on cuda raises the test PSNR over the model it starts from (one step in), that a run stopped
half way resumes to the end with the same iteration log, and that its final PSNR is within 0.5 dB of the uninterrupted
run (the CUDA backward sums with float atomics, so the two runs are not bitwise equal). Prints one JSON line with the
numbers; exit 1 on failure.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--backend", default="cuda", help="cuda; cpu for a dry run of the script itself")
    ap.add_argument("--num-primitives", type=int, default=4000)
    ap.add_argument("--min-gain", type=float, default=3.0,
                    help="dB the test PSNR must gain over the starting model's (0 for a dry run's few steps)")
    args = ap.parse_args(argv)
    from splatzoo.data import load_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig
    from splatzoo.training.trainer import test_psnr

    if args.backend == "cuda" and not torch.cuda.is_available():
        print("no CUDA device", file=sys.stderr)
        return 1
    if args.iterations < 4:
        ap.error("--iterations must be at least 4 (the run stops half way and resumes)")
    scene = load_scene(args.data)
    cfg = TrainConfig(iterations=args.iterations, backend=args.backend, num_primitives=args.num_primitives,
                      densify=True, seed=1, log_every=min(50, max(1, args.iterations // 10)),
                      eval_every=args.iterations // 2)
    # the model training starts from, one step in (the log's first training PSNRs are many steps in: at 50 and 100)
    start = train(scene, "gabor", {}, cfg, f"{args.out}/start", progress=False, evaluate_at_end=False, stop_after=1)
    psnr_start = test_psnr(start.model, scene, args.backend)
    t0 = time.perf_counter()
    full = train(scene, "gabor", {}, cfg, f"{args.out}/full", progress=False, evaluate_at_end=False)
    seconds = time.perf_counter() - t0
    train(scene, "gabor", {}, cfg, f"{args.out}/part", progress=False, evaluate_at_end=False,
          stop_after=args.iterations // 2)
    resumed = train(scene, "gabor", {}, None, f"{args.out}/part", resume=True, progress=False, evaluate_at_end=False)
    log = lambda run: [json.loads(x) for x in open(f"{args.out}/{run}/train_log.jsonl")]  # noqa: E731
    psnr_full = test_psnr(full.model, scene, args.backend)
    psnr_resumed = test_psnr(resumed.model, scene, args.backend)
    same_log = [r["iteration"] for r in log("full")] == [r["iteration"] for r in log("part")]
    report = {"iterations": args.iterations, "seconds": round(seconds, 2),
              "its_per_s": round(args.iterations / seconds, 1),
              "test_psnr_start": round(psnr_start, 3), "test_psnr": round(psnr_full, 3),
              "test_psnr_resumed": round(psnr_resumed, 3),
              "primitives": full.model.num_primitives, "same_iteration_log": same_log,
              "device": torch.cuda.get_device_name() if args.backend == "cuda" else args.backend}
    ok = same_log and psnr_full > psnr_start + args.min_gain and abs(psnr_full - psnr_resumed) < 0.5
    report["ok"] = ok
    print(json.dumps(report))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
