"""Removed waves cost nothing: native CPU rasterizer time for Gabor K=4 surfels with per-surfel wave counts
(all 4, 2, 1, 0) against 2DGS surfels (K=0), on the benchmark's 128x128 / 5k scene.

    python benchmarks/bench_wave_counts.py [--repeats 7] [--surfels 5000] [--size 128]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rasterizer import _time, random_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--surfels", type=int, default=5000)
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args(argv)
    from splatzoo.rasterizers import rasterize
    from splatzoo.types import Surfels

    s4, cam = random_scene(args.surfels, args.size, args.size, 4, seed=1)
    rows = [("K=0 (2dgs)", Surfels(s4.means, s4.quats, s4.scales, s4.opacities, s4.base_color, s4.wave_vectors[:, :0],
                                    s4.wave_phases[:, :0], s4.wave_amplitudes[:, :0]))]
    for c in (4, 2, 1, 0):
        rows.append((f"K=4, counts {c}", Surfels(*s4.tensors().values(), wave_counts=torch.full((s4.num,), c))))
    rows.append(("K=4, no counts", s4))
    print(f"{'surfels':<18}{'fwd ms':>10}{'fwd+bwd ms':>12}   ({args.size}x{args.size}, {args.surfels} surfels, "
          f"{torch.get_num_threads()} threads, median of {args.repeats})")
    for name, s in rows:
        s = s.map(lambda t: t.detach().requires_grad_(True))

        def fwd_bwd():
            out = rasterize(s, cam, backend="cpu")
            (out.rgb.sum() + out.depth.sum()).backward()

        t_f = _time(lambda: rasterize(s, cam, backend="cpu"), args.repeats, lambda: None)
        t_fb = _time(fwd_bwd, args.repeats, lambda: None)
        print(f"{name:<18}{t_f:>10.1f}{t_fb:>12.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
