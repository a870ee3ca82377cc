"""Side by side on one GPU: splatzoo's cuda backend (K=0, i.e. 2DGS) and gsplat's 2DGS rasterizer on the same
surfels, forward and forward+backward at 1920x1080.

    python benchmarks/bench_gsplat.py [--sizes 100000,500000,1000000] [--repeats 10] [--json out.json]

gsplat must be importable (e.g. its source distribution on PYTHONPATH: it compiles its CUDA code on first import).
Both sides render colour, depth, normals and the distortion term and back-propagate a loss on all of them:
splatzoo `rasterize(..., backend="cuda")`; gsplat `rasterization_2dgs(render_mode="RGB+ED", distloss=True)`,
which also computes normals from the rendered depth. Surfels: the benchmark's sphere-and-wall scene (1-4 px sigma).
Times are CUDA-synchronised wall clock, median of --repeats after two warm-ups.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rasterizer import machine_info, make_scene  # noqa: E402


def _time(fn, repeats):
    for _ in range(2):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="100000,500000,1000000")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", default="benchmarks/results/gsplat.json")
    args = ap.parse_args(argv)
    import gsplat

    from splatzoo.rasterizers import rasterize

    rows = []
    print(f"gsplat {gsplat.__version__} on {torch.cuda.get_device_name()}")
    print(f"{'surfels':>9} {'ours fwd':>9} {'gsplat fwd':>11} {'ratio':>6} {'ours f+b':>9} {'gsplat f+b':>11} {'ratio':>6}")
    for n in (int(x) for x in args.sizes.split(",")):
        scene, cam = make_scene("sphere", n, args.width, args.height, "0", seed=n)
        s = scene.to("cuda").map(lambda t: t.detach().requires_grad_(True))
        camc = cam.to("cuda", torch.float32)
        viewmats, Ks = camc.world_to_camera[None].contiguous(), camc.K[None].contiguous()
        g_scales = torch.cat([s.scales.detach(), torch.ones_like(s.scales[:, :1])], 1).requires_grad_(True)
        g_quats = s.quats.detach().clone().requires_grad_(True)
        g_means = s.means.detach().clone().requires_grad_(True)
        g_opac = s.opacities.detach().clone().requires_grad_(True)
        g_col = s.base_color.detach().clone().requires_grad_(True)  # gsplat wants colours per camera: [1,N,3] below

        def ours(backward):
            out = rasterize(s, cam, backend="cuda")
            if backward:
                (out.rgb.sum() + out.depth.sum() + out.normal.sum() + out.distortion.sum()).backward()

        def theirs(backward):
            colors, alphas, normals, normals_from_depth, distort, median, _ = gsplat.rasterization_2dgs(
                g_means, g_quats, g_scales, g_opac, g_col[None], viewmats, Ks, args.width, args.height,
                near_plane=0.2, render_mode="RGB+ED", distloss=True)
            if backward:
                (colors.sum() + normals.sum() + distort.sum()).backward()

        def nograd(fn):
            def run():
                with torch.no_grad():
                    fn(False)
            return run

        row = {"surfels": n, "width": args.width, "height": args.height,
               "ours_forward_ms": _time(nograd(ours), args.repeats),
               "gsplat_forward_ms": _time(nograd(theirs), args.repeats),
               "ours_forward_backward_ms": _time(lambda: ours(True), args.repeats),
               "gsplat_forward_backward_ms": _time(lambda: theirs(True), args.repeats)}
        rows.append(row)
        print(f"{n:>9} {row['ours_forward_ms']:>9.2f} {row['gsplat_forward_ms']:>11.2f} "
              f"{row['ours_forward_ms'] / row['gsplat_forward_ms']:>6.2f} {row['ours_forward_backward_ms']:>9.2f} "
              f"{row['gsplat_forward_backward_ms']:>11.2f} "
              f"{row['ours_forward_backward_ms'] / row['gsplat_forward_backward_ms']:>6.2f}")
        del s, g_means, g_quats, g_scales, g_opac, g_col
        torch.cuda.empty_cache()
    print("ratio = ours / gsplat (below 1: ours is faster)")
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"machine": machine_info(), "gsplat": gsplat.__version__, "date": time.strftime("%Y-%m-%d %H:%M"),
                                "results": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
