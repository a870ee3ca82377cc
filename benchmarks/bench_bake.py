"""The `baked` export: a gabor run baked into plain constant-colour splats (`splatzoo.bake`), scored against the test
views' ground truth next to gabor itself and its plain export (waves dropped), with the bake error (PSNR of the
baked render against gabor's own, on held-out jittered views), splat counts, PLY bytes and bake time.

    nice -n 10 env OMP_NUM_THREADS=1 splatzoo synth sweater --out /tmp/bake/data --views 24 --width 128 --height 128
    nice -n 10 env OMP_NUM_THREADS=1 splatzoo train /tmp/bake/data --model gabor --n-waves 4 --iterations 1500 \\
        --no-densify --num-primitives 2000 --out /tmp/bake/gabor
    nice -n 10 env OMP_NUM_THREADS=1 python benchmarks/bench_bake.py /tmp/bake/gabor [--max-splats 16000] \\
        [--steps 1500,300,0] [--seed 0]

Each --steps value is one bake (0: the split alone, no fit). "plain" is gabor rendered with its waves dropped (each
surfel's base colour): what a constant-colour viewer shows of the plain export.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a finished gabor run folder (splatzoo train --model gabor)")
    ap.add_argument("--max-splats", type=int, default=None, help="the bake's cap (default 8x the surfels)")
    ap.add_argument("--steps", default="1500", help="fit steps, one bake per comma-separated value")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    import torch

    from splatzoo.bake import BakeOptions, bake_model, waves_dropped
    from splatzoo.export import save_ply
    from splatzoo.metrics import psnr
    from splatzoo.runs import Run

    run = Run(args.run)
    model, scene, _ = run.load("auto")
    cams = [v.camera for v in scene.train]

    def gt_psnr(m, surfels_of=None) -> float:
        vals = []
        for v in scene.test:
            extra = {}
            if surfels_of is not None:
                p = next(m.parameters())
                extra["surfels"] = surfels_of(v.camera.to(p.device, p.dtype))
            vals.append(psnr(m.render(v.camera, image_only=True, **extra).image().cpu(), v.image_float()))
        return sum(vals) / len(vals)

    with tempfile.TemporaryDirectory() as tmp:
        src_bytes = save_ply(model, Path(tmp) / "gabor.ply").stat().st_size
        print(f"{run.path.name}: {model.name}, {model.num_primitives} surfels, {len(scene.test)} test views "
              f"{scene.test[0].camera.width}x{scene.test[0].camera.height}, {len(cams)} training cameras")
        print("| model | splats | PLY bytes | PSNR vs GT | bake error (dB vs gabor render) | bake seconds |")
        print("|---|---|---|---|---|---|")
        print(f"| gabor | {model.num_primitives} | {src_bytes:,} | {gt_psnr(model):.2f} | | |", flush=True)
        print(f"| plain export (waves dropped) | {model.num_primitives} | | {gt_psnr(model, waves_dropped(model)):.2f} "
              "| | |", flush=True)
        for steps in (int(s) for s in args.steps.split(",")):
            t0 = time.perf_counter()
            baked, report = bake_model(model, cams, BakeOptions(max_splats=args.max_splats, steps=steps,
                                                                seed=args.seed))
            seconds = time.perf_counter() - t0
            size = save_ply(baked, Path(tmp) / f"baked{steps}.ply").stat().st_size
            with torch.no_grad():
                score = gt_psnr(baked)
            print(f"| baked, {steps} steps | {report['splats']} (cap {report['max_splats']}) | {size:,} | "
                  f"{score:.2f} | {report['bake_db']:.2f} (split alone {report['start_db']:.2f}, waves dropped "
                  f"{report['plain_db']:.2f}) | {seconds:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
