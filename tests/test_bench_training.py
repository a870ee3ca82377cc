"""benchmarks/bench_training.py (also `splatzoo bench --training`) at a toy size: every part of a step is timed, the
parts add up to the step, host syncs are counted, and a missing gsplat trainer is reported, not fatal."""
import importlib.util
import json
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_training.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_training", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_training_benchmark_runs_end_to_end_with_a_breakdown(tmp_path):
    bench = _bench()
    lines = []
    results = bench.run(["--width", "32", "--height", "24", "--views", "5", "--iterations", "4", "--backend", "cpu",
                         "--breakdown-steps", "3", "--work", str(tmp_path), "--gsplat-examples", str(tmp_path / "no")],
                        echo=lines.append)
    assert set(results["train"]) == {"2dgs", "gabor", "gsplat 2dgs"}
    assert "not found" in results["train"]["gsplat 2dgs"]["error"]
    for model in ("2dgs", "gabor"):
        r = results["train"][model]
        assert r["train_s"] > 0 and r["it_per_s"] > 0 and r["psnr"] > 5 and r["primitives"] > 0
        b = results["breakdown"][model]
        assert set(b["parts_ms"]) == set(bench.PARTS)
        assert b["parts_ms"]["raster fwd"] > 0 and b["parts_ms"]["raster bwd"] > 0 and b["parts_ms"]["data"] > 0
        assert abs(sum(b["parts_ms"].values()) - b["step_ms"]) < 1e-6 * max(1.0, b["step_ms"])
        assert 0 < b["host_syncs_per_step"] <= 8
    assert json.loads((tmp_path / "training.json").read_text())["iterations"] == 4
    assert any(line.startswith("splatzoo gabor") for line in lines) and any("gabor / 2dgs" in line for line in lines)
    # the timers are gone afterwards: the classes and modules have their own functions back
    from splatzoo.data.scene import View
    from splatzoo.rasterizers import native
    from splatzoo.training import trainer

    assert not hasattr(View.image_float, "__wrapped__") and View.image_float.__qualname__ == "View.image_float"
    assert trainer.photometric_loss.__module__ != BENCH.stem and native._RenderFn.forward.__name__ == "forward"


def test_bench_training_command_checks_its_size():
    from typer.testing import CliRunner

    from splatzoo.cli import app

    r = CliRunner().invoke(app, ["bench", "--training", "--size", "1920by1080"])
    assert r.exit_code != 0 and "WIDTHxHEIGHT" in str(r.exception)
