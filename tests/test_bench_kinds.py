"""The cost-per-member benchmarks at a toy size: bench_rasterizer's scenes for every member's appearance kind
(plain, Beta kernel, waves, texture) are valid surfels, and bench_kinds.py times trained runs side by side."""
import importlib.util
from pathlib import Path

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("waves", ["0", "0b", "4", "6", "0t4", "4ab"])
def test_rasterizer_benchmark_scenes_for_every_member(waves):
    from splatzoo.rasterizers import rasterize

    bench = _load("bench_rasterizer")
    s, cam = bench.make_scene("sphere", 64, 32, 32, waves, seed=3)
    s.validate()
    beta = waves.endswith("b")
    assert s.falloff is not None and bool((s.falloff > 0).all()) == beta  # zeros: the Gaussian
    if beta:
        assert 0.3 <= float(s.falloff.min()) and float(s.falloff.max()) <= 1.0
    assert (s.texture.shape[1] == 4) == ("t" in waves)  # no texture: an empty [N,0,0,4]
    assert s.wave_vectors.shape[1] == bench.parse_waves(waves)[0] == int(waves[0])
    out = rasterize(s, cam, backend="cpu")
    assert torch.isfinite(out.rgb).all() and out.alpha.max() > 0


def test_bench_kinds_times_trained_runs_side_by_side(tmp_path, capsys):
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training.trainer import TrainConfig

    data = make_synthetic_scene("plain", tmp_path / "data", views=6, width=32, height=32)
    cfg = TrainConfig(iterations=3, backend="cpu", num_primitives=60, densify=False)
    for model in ("2dgs", "beta"):
        train(data, model, {}, cfg, tmp_path / model, progress=False, evaluate_at_end=False)
    assert _load("bench_kinds").main([str(tmp_path / "2dgs"), str(tmp_path / "beta"), "--backend", "cpu",
                                      "--views", "2", "--rounds", "2"]) == 0
    rows = {line.split("|")[1].strip(): line.split("|")[2:-1] for line in capsys.readouterr().out.splitlines()
            if line.startswith("| 2dgs") or line.startswith("| beta")}
    assert set(rows) == {"2dgs", "beta"}
    assert rows["2dgs"][0].strip() == "60" and rows["2dgs"][1].strip() == "32x32"
    assert [c.strip() for c in rows["2dgs"][4:6]] == ["1.00", "1.00"]
    assert all(float(c) > 0 for c in rows["beta"][2:6])
