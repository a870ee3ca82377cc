"""What each member of the zoo costs to render and to train through, on its own trained surfels: forward (every
output, as training's forward) and forward+backward of `model.render` (the member's surfels, then the rasterizer)
at its run's training views, one run against the others in the same process, interleaved round by round so that a
noisy machine slows them alike. Prints a table with ratios to the first run.

    python benchmarks/bench_kinds.py RUN [RUN ...] [--backend cpu] [--views 6] [--rounds 5]

RUN: finished run folders (`splatzoo train` or `compare` output, e.g. OUT/runs/2dgs).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--backend", default="auto", help="auto, cpu or cuda")
    ap.add_argument("--views", type=int, default=6, help="training views rendered per timing")
    ap.add_argument("--rounds", type=int, default=5, help="timed rounds (the median is reported)")
    args = ap.parse_args(argv)
    import torch

    from splatzoo.rasterizers import resolve_backend
    from splatzoo.runs import load_run

    members = []
    for path in args.runs:
        model, scene, _ = load_run(path, args.backend)
        device = next(model.parameters()).device
        backend = resolve_backend(args.backend, device)
        cams = [v.camera.to(device, torch.float32) for v in scene.train[:args.views]]
        bg = torch.tensor(scene.background, dtype=torch.float32, device=device)
        members.append({"label": path.name, "model": model, "cams": cams, "bg": bg, "fwd": [], "both": [],
                        "surfels": model.num_primitives, "size": f"{cams[0].width}x{cams[0].height}"})
    sync = torch.cuda.synchronize if backend == "cuda" else (lambda: None)

    def forward(m):
        with torch.no_grad():
            for c in m["cams"]:
                m["model"].render(c, background=m["bg"], backend=backend)

    def forward_backward(m):
        for c in m["cams"]:
            out = m["model"].render(c, background=m["bg"], backend=backend)
            (out.rgb.sum() + out.alpha.sum()).backward()
        m["model"].zero_grad(set_to_none=True)

    def timed(fn, m) -> float:
        sync()
        t0 = time.perf_counter()
        fn(m)
        sync()
        return (time.perf_counter() - t0) * 1e3 / len(m["cams"])

    for m in members:  # warm-up: first calls build caches and load kernels
        forward(m)
        forward_backward(m)
    for _ in range(args.rounds):
        for m in members:
            m["fwd"].append(timed(forward, m))
            m["both"].append(timed(forward_backward, m))
    ref = members[0]
    ref_fwd, ref_both = statistics.median(ref["fwd"]), statistics.median(ref["both"])
    print(f"backend {backend}, {torch.get_num_threads()} threads, {args.views} views, median of {args.rounds} rounds, "
          f"ms per view")
    print(f"| run | surfels | view | fwd ms | fwd+bwd ms | fwd / {ref['label']} | fwd+bwd / {ref['label']} |")
    print("|---|---|---|---|---|---|---|")
    for m in members:
        f, b = statistics.median(m["fwd"]), statistics.median(m["both"])
        print(f"| {m['label']} | {m['surfels']} | {m['size']} | {f:.1f} | {b:.1f} | {f / ref_fwd:.2f} | "
              f"{b / ref_both:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
