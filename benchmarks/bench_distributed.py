"""Training throughput against the number of processes and the batch size, on this machine.

    python benchmarks/bench_distributed.py [--iterations 200] [--size 128]

Trains gabor on the built-in sweater scene (fixed count, 2000 surfels) as (nproc, batch) = (1, 1), (1, 2), (2, 1)
and prints views per second, seconds per step and the bytes each rank all-reduces per step (the flat gradient).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args(argv)
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    with tempfile.TemporaryDirectory() as tmp:
        data = make_synthetic_scene("sweater", Path(tmp) / "data", views=24, width=args.size, height=args.size)
        print(f"sweater {args.size}x{args.size}, gabor, 2000 surfels, {args.iterations} steps")
        print("| processes | views per process per step | views/s | s per step | all-reduce bytes per step |")
        print("|---|---|---|---|---|")
        for nproc, batch in ((1, 1), (1, 2), (2, 1)):
            cfg = TrainConfig(iterations=args.iterations, num_primitives=2000, densify=False, backend="cpu",
                              nproc=nproc, batch_size=batch, eval_every=10 ** 9, log_every=10 ** 9)
            t0 = time.perf_counter()
            result = train(data, "gabor", {}, cfg, Path(tmp) / f"n{nproc}b{batch}", progress=False,
                           evaluate_at_end=False)
            seconds = time.perf_counter() - t0
            params = sum(p.numel() for p in result.model.parameters())
            views = args.iterations * nproc * batch
            print(f"| {nproc} | {batch} | {views / seconds:.1f} | {seconds / args.iterations:.3f} | "
                  f"{4 * params if nproc > 1 else 0} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
