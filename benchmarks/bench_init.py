"""Initial surfel scales (the mean distance to the 3 nearest points) against the point count: the KD-tree of
splatzoo.models.base.nearest_neighbour_distance beside the all-pairs search it replaced (chunked torch.cdist, run
only up to --max-brute points; it is quadratic).

    python benchmarks/bench_init.py [--counts 10000,100000,1000000] [--max-brute 100000]
"""
from __future__ import annotations

import argparse
import time

import torch

from splatzoo.models.base import nearest_neighbour_distance


def brute_force(points: torch.Tensor, k: int = 3, chunk: int = 2048) -> torch.Tensor:
    out = []
    for i in range(0, points.shape[0], chunk):
        d = torch.cdist(points[i:i + chunk], points)
        d[torch.arange(d.shape[0]), torch.arange(i, i + d.shape[0])] = float("inf")
        out.append(d.topk(k, largest=False).values.mean(1))
    return torch.cat(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", default="10000,100000,1000000")
    ap.add_argument("--max-brute", type=int, default=100000)
    args = ap.parse_args()
    print(f"torch threads {torch.get_num_threads()}")
    print(f"{'points':>10}{'kd-tree s':>12}{'all-pairs s':>13}{'ratio':>8}{'max rel diff':>14}")
    for n in (int(c) for c in args.counts.split(",")):
        pts = torch.rand(n, 3, generator=torch.Generator().manual_seed(0))
        t0 = time.perf_counter()
        tree = nearest_neighbour_distance(pts)
        t_tree = time.perf_counter() - t0
        if n <= args.max_brute:
            t0 = time.perf_counter()
            brute = brute_force(pts)
            t_brute = time.perf_counter() - t0
            diff = float(((tree - brute).abs() / brute).max())
            print(f"{n:>10}{t_tree:>12.3f}{t_brute:>13.2f}{t_brute / t_tree:>8.0f}{diff:>14.1e}")
        else:
            print(f"{n:>10}{t_tree:>12.3f}{'-':>13}{'-':>8}{'-':>14}")


if __name__ == "__main__":
    main()
