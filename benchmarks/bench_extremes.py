"""How far apart the backends are at the extremes of each surfel field: one tilted surfel (two waves) rendered by
the reference and by every native backend, plain and anti-aliased, with a short (24 px image, 50 degrees) and a very
long (0.05 degrees) focal length. For each value it prints the reference's total alpha and, per native backend, the
largest alpha difference and the largest gradient difference relative to the largest reference gradient (scales as
d/d log s, the gradient a model sees).

    python benchmarks/bench_extremes.py [--fields scale,freq,means]

The valid ranges (splatzoo/types.py: MAX_SCALE, MAX_WAVE_NUMBER, ...) are where these stay at float rounding;
beyond them Surfels.validate refuses the values, so this script builds its surfels without that check.
"""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from splatzoo import Camera, Surfels  # noqa: E402
from splatzoo.geometry import normals_to_quats  # noqa: E402
from splatzoo.rasterizers import BACKENDS  # noqa: E402
from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS  # noqa: E402

NATIVE = ("cpu", "cuda-emulated")


def surfel(center=(0.0, 0.0, 0.0), scale=(0.3, 0.2), waves=((3.0, 1.0), (0.5, 2.0))) -> Surfels:
    f = lambda v: torch.tensor([v], dtype=torch.float32)  # noqa: E731
    k = len(waves)
    return Surfels(f(center), normals_to_quats(f((0.3, 0.2, -1.0))), f(scale), f(0.8), f((0.5, 0.4, 0.3)),
                   f(waves).reshape(1, k, 2), torch.full((1, k), 0.3), torch.full((1, k, 3), 0.2))


def compare(s: Surfels, cam: Camera, settings) -> str:
    g = torch.Generator().manual_seed(0)
    cot = torch.randn(cam.height, cam.width, 3, generator=g), torch.randn(cam.height, cam.width, generator=g)
    res = {}
    for name in ("reference",) + NATIVE:
        leaves = {k: v.clone().requires_grad_(True) for k, v in s.tensors().items()}
        out = BACKENDS.get(name).render(Surfels(**leaves), cam.detach(), None, settings)  # no range check
        ((out.rgb * cot[0]).sum() + (out.alpha * cot[1]).sum()).backward()
        grads = {k: v.grad * (s.scales if k == "scales" else 1) for k, v in leaves.items() if v.numel()}
        res[name] = out.alpha.detach(), grads
    alpha, g_ref = res["reference"]
    largest = max(float(v.abs().max()) for v in g_ref.values()) or 1.0
    line = f"ref alpha {float(alpha.sum()):8.4g}"
    for name in NATIVE:
        a, gr = res[name]
        dg = max(float((gr[k] - g_ref[k]).abs().max()) for k in g_ref) / largest
        line += f" | {name}: alpha {float((a - alpha).abs().max()):.1e} grad {dg:.1e}"
    return line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fields", default="scale,freq,means")
    fields = ap.parse_args().fields.split(",")
    for st_name, st in (("plain", SETTINGS), ("anti-aliased", ANTIALIASED)):
        for fov in (50.0, 0.05):
            cam = Camera.look_at([0, 0, -3.0], [0, 0, 0], width=24, height=24, fov_deg=fov, dtype=torch.float32)
            head = f"{st_name:12s} focal {float(cam.K[0, 0]):8.3g} px"
            if "scale" in fields:
                for e in range(0, 22, 2):
                    sc = 10.0 ** e
                    print(f"{head} scale 1e{e:<3d}", compare(surfel(scale=(sc, sc / 2)), cam, st), flush=True)
            if "freq" in fields:
                for e in range(1, 8):
                    k = 10.0 ** e
                    print(f"{head} wave number 1e{e}", compare(surfel(waves=((k, 0.3 * k), (0.1 * k, k))), cam, st),
                          flush=True)
            if "means" in fields:
                for e in range(0, 14, 2):
                    d = 10.0 ** e
                    near = Camera.look_at([d, d, d - 3.0], [d, d, d], width=24, height=24, fov_deg=fov)
                    print(f"{head} position 1e{e}", compare(surfel(center=(d, d, d)), near, st), flush=True)


if __name__ == "__main__":
    main()
