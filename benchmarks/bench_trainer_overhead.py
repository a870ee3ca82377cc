"""The trainer's own cost per iteration: the share of a training step spent outside the rasterizer (its forward and
hand-written backward), and the host syncs per step, for 2dgs and gabor on a built-in synthetic scene.

    python benchmarks/bench_trainer_overhead.py [--scene sweater --size 256 --views 24 --steps 60 --backend cpu]

Steps are timed after a warm-up, between densifications (--no-densify); the rasterizer's time is measured by
wrapping the native forward and backward, so everything else (the model's surfels, losses, autograd of the model's
parameter maps, Adam, bookkeeping) is the trainer's overhead.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from splatzoo.data import load_scene
from splatzoo.data.synthetic import make_synthetic_scene
from splatzoo.rasterizers import native
from splatzoo.testing import HostSyncs
from splatzoo.training.trainer import TrainConfig, Trainer
from splatzoo.zoo import make_config


class RasterTimer:
    """Adds up the wall time of native._RenderFn's forward and backward while active."""

    def __init__(self) -> None:
        self.seconds = 0.0

    def __enter__(self):
        self._fwd, self._bwd = native._RenderFn.forward, native._RenderFn.backward
        timer = self

        def timed(fn):
            def run(*args):
                t0 = time.perf_counter()
                try:
                    return fn(*args)
                finally:
                    timer.seconds += time.perf_counter() - t0
            return staticmethod(run)

        native._RenderFn.forward = timed(self._fwd)
        native._RenderFn.backward = timed(self._bwd)
        return self

    def __exit__(self, *exc):
        native._RenderFn.forward, native._RenderFn.backward = staticmethod(self._fwd), staticmethod(self._bwd)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="sweater")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--num-primitives", type=int, default=20000)
    ap.add_argument("--backend", default="cpu")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = make_synthetic_scene(args.scene, Path(tmp) / "data", views=args.views, width=args.size,
                                    height=args.size)
        scene = load_scene(data)
        print(f"{args.scene} {args.size}x{args.size}, {args.num_primitives} surfels, backend {args.backend}, "
              f"torch threads {torch.get_num_threads()}")
        print(f"{'model':<8}{'step ms':>9}{'raster ms':>11}{'other ms':>10}{'other share':>13}{'syncs/step':>12}")
        for model in ("2dgs", "gabor"):
            cfg = TrainConfig(iterations=10 * args.steps, backend=args.backend, densify=False,
                              num_primitives=args.num_primitives)
            device = torch.device("cuda" if args.backend == "cuda" else "cpu")
            trainer = Trainer.start(scene, model, make_config(model), cfg, args.backend, device)
            for _ in range(5):
                trainer.step()
            with HostSyncs() as syncs:
                trainer.step()
            sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
            sync()
            with RasterTimer() as raster:
                t0 = time.perf_counter()
                for _ in range(args.steps):
                    trainer.step()
                sync()
                total = time.perf_counter() - t0
            step, ras = 1000 * total / args.steps, 1000 * raster.seconds / args.steps
            print(f"{model:<8}{step:>9.1f}{ras:>11.1f}{step - ras:>10.1f}{(step - ras) / step:>13.0%}"
                  f"{syncs.total:>12}")


if __name__ == "__main__":
    main()
