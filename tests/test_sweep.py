"""`splatzoo sweep`: the (waves x primitives) grid writes sweep.json, pareto.png and report.md."""
import json

import pytest
from typer.testing import CliRunner

from splatzoo.cli import app
from splatzoo.errors import SplatzooError
from splatzoo.sweep import grid_choice, mark_pareto, parse_int_list


def test_sweep_cli_on_a_tiny_scene(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "tiny", views=6, width=32, height=32)
    out = tmp_path / "sweep"
    r = CliRunner().invoke(app, ["sweep", str(data), "--model", "gabor", "--n-waves", "0,2", "--num-primitives",
                                 "40,80", "--iterations", "10", "--out", str(out), "--prune-waves", "0.001"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    assert f"wrote {out}" in r.output
    for name in ("sweep.json", "pareto.png", "report.md"):
        assert (out / name).stat().st_size > 0, name
    result = json.loads((out / "sweep.json").read_text())
    pts = result["points"]
    assert {(p["n_waves"], p["num_primitives"]) for p in pts} == {(0, 40), (0, 80), (2, 40), (2, 80)}
    assert {p["label"] for p in pts} == {"2dgs", "gabor:n_waves=2,prune_waves=0.001"}
    assert result["settings"]["model_options"] == {"prune_waves": "0.001"}
    assert all(p["render_ms"] > 0 and p["size_bytes"] > 0 for p in pts)
    assert any(p["pareto_time"] for p in pts) and any(p["pareto_size"] for p in pts)
    assert "| n_waves | primitives |" in (out / "report.md").read_text()
    # same initial points per count: every run of a count starts from that many primitives
    for n in (40, 80):
        cfg = json.loads((out / f"n{n}" / "runs" / "2dgs" / "config.json").read_text())
        assert cfg["train"]["num_primitives"] == n and cfg["train"]["densify"] is False


def test_pareto_front_and_parsing():
    pts = [{"psnr": 20.0, "c": 1.0}, {"psnr": 22.0, "c": 2.0}, {"psnr": 21.0, "c": 3.0}, {"psnr": 22.0, "c": 2.5}]
    mark_pareto(pts, "c", "front")
    assert [p["front"] for p in pts] == [True, True, False, False]
    assert parse_int_list("0, 1,4", "x") == [0, 1, 4] and grid_choice("gabor", 0).model == "2dgs"
    with pytest.raises(SplatzooError, match="integers"):
        parse_int_list("1,a", "--n-waves")


def test_sweep_antialiased(tmp_path):
    """--antialias reaches every run of the grid, the record and the report."""
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "tiny", views=6, width=32, height=32)
    out = tmp_path / "sweep"
    r = CliRunner().invoke(app, ["sweep", str(data), "--n-waves", "0,2", "--num-primitives", "40", "--iterations",
                                 "4", "--out", str(out), "--antialias", "--backend", "cpu"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    assert json.loads((out / "sweep.json").read_text())["settings"]["antialias"] is True
    assert "anti-aliased" in (out / "report.md").read_text()
    for run in ("2dgs", "gabor_n_waves_2"):
        assert json.loads((out / "n40" / "runs" / run / "config.json").read_text())["train"]["antialias"] is True
