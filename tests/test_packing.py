"""Models stored at reduced precision (.szp packed files): what a file loads back as is exactly what training and
evaluation used, sizes are the files' own, quantisation stays within its step, budgets are never exceeded, and a
damaged or crafted packed file is a named error."""
import hashlib
import json
import math
import struct
import zlib

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from splatzoo import create_model, load_model, save_model
from splatzoo.cli import app
from splatzoo.compare import ModelChoice, budget_count, parse_budgets, stored_cost
from splatzoo.errors import SplatzooError
from splatzoo import packing
from splatzoo.packing import (PRECISIONS, encoding_for, header_dictionary, pack_checkpoint, quantise_tensor,
                              read_header, unpack_checkpoint)
from splatzoo.registry import MODELS
from splatzoo.zoo import make_config, stored_bytes, stored_copy, stored_values

BUILTINS = [n for n in MODELS.names() if MODELS.get(n).cls.__module__.startswith("splatzoo.")]


def trained_looking(name, n=40, seed=0, **options):
    """A model whose every parameter is off its initial value (so each column has a range to quantise)."""
    g = torch.Generator().manual_seed(seed)
    model = create_model(name, torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), **options)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    if getattr(model, "adaptive", False):  # some surfels wave-less, the rest with a few waves: the packed layout
        slots = model.active_slots().shape  # [N, width] (per-wave weights have a colour axis besides)
        drop = torch.rand(slots, generator=g) < 0.6
        drop[: n // 4] = True
        model.prune_waves(0.0, remove=drop)
        assert 0 < int(model.wave_counts.sum()) < slots.numel() and int((model.wave_counts == 0).sum())
    model.antialias, model.background = True, (1.0, 1.0, 1.0)
    return model


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name", BUILTINS)
def test_the_file_loads_back_as_the_stored_copy(name, precision, tmp_path):
    model = trained_looking(name)
    model.precision = precision
    path = tmp_path / "m.szp"
    save_model(model, path)
    back, expected = load_model(path), stored_copy(model, precision)
    assert path.stat().st_size == stored_bytes(model) == stored_bytes(model, precision)
    assert back.precision == precision and back.antialias and back.background == (1.0, 1.0, 1.0)
    assert back.state_dict().keys() == model.state_dict().keys()
    for k, v in expected.state_dict().items():
        assert torch.equal(back.state_dict()[k], v), k
    if precision == "float32":
        for k, v in model.state_dict().items():
            assert torch.equal(back.state_dict()[k], v), k
    # packed again, stored values move by float32 rounding at most
    again = stored_copy(back, precision)
    for k, v in back.state_dict().items():
        if v.is_floating_point():
            assert torch.allclose(again.state_dict()[k], v, rtol=1e-6, atol=1e-6), k
        else:
            assert torch.equal(again.state_dict()[k], v), k


def test_sizes_per_precision():
    """2dgs stores 13 numbers a surfel: 52 bytes as float32, 26 as float16 (positions at 16 bits: 6 bytes), 16 at
    8 bits (positions 6, scales 2, rotation 4, opacity 1, colour 3); the header is shared."""
    per = {}
    for precision in PRECISIONS:   # the compressed header may differ by a few bytes (the shapes' digits)
        per[precision] = (stored_cost(ModelChoice("2dgs", "2dgs"), 1100, precision) -
                          stored_cost(ModelChoice("2dgs", "2dgs"), 100, precision)) / 1000
    assert per == pytest.approx({"float32": 52, "float16": 26, "8bit": 16}, abs=0.03)
    assert stored_cost(ModelChoice("2dgs", "2dgs"), 1, "8bit") < 220   # the header, compressed, and column ranges
    model = trained_looking("2dgs", n=1000)
    assert stored_bytes(model, "8bit") < 0.32 * stored_bytes(model, "float32")


def test_quantisation_error_is_within_half_a_step():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1000, 3, generator=g) * torch.tensor([1.0, 10.0, 1e-3])
    for name, bits in (("means", 16), ("sh_dc", 8)):
        q = quantise_tensor(name, x, "8bit")
        step = (x.max(0).values - x.min(0).values) / (2**bits - 1)
        # 8-bit ranges as half floats: a step up to 2^-11 coarser
        assert ((q - x).abs() <= step / 2 * 1.0005 + 1e-7).all(), name
        assert q.dtype == x.dtype and q.shape == x.shape
    assert torch.equal(quantise_tensor("sh_dc", x, "float32"), x)
    half = quantise_tensor("sh_dc", x, "float16")
    assert torch.equal(half, x.half().float())
    assert torch.equal(quantise_tensor("wave_counts", torch.arange(5, dtype=torch.int32), "8bit"),
                       torch.arange(5, dtype=torch.int32))
    const = torch.full((7, 2), 0.25)   # a column with no range: stored exactly
    assert torch.equal(quantise_tensor("sh_dc", const, "8bit"), const)


def test_8bit_column_ranges_are_half_floats_only_where_they_store_as_well(tmp_path):
    """A column's minimum and step take 4 bytes as half floats, 8 as float32; half floats are used where they move
    no value by more than the code's own rounding (half a step), and a file's values pack again to the same ones."""
    g = torch.Generator().manual_seed(5)
    near = torch.randn(500, 3, generator=g)                    # around zero: half floats store its range
    far = 1000.3 + torch.rand(500, 3, generator=g)             # a span of 1 at 1000: a half float steps by 0.5 there
    fine = 1e-9 * torch.rand(500, 3, generator=g)              # a step below a half float's resolution
    huge = 1e6 * torch.randn(500, 3, generator=g)              # beyond a half float's range
    assert encoding_for("sh_dc", near, "8bit") == "u8h"
    for x in (far, fine, huge):
        assert encoding_for("sh_dc", x, "8bit") == "u8"
    for x in (near, far, fine, huge):
        q = quantise_tensor("sh_dc", x, "8bit")
        step = (x.max(0).values - x.min(0).values) / 255
        assert ((q - x).abs() <= step / 2 * 1.0005 + 1e-12 * x.abs().max()).all()
        assert torch.equal(quantise_tensor("sh_dc", q, "8bit"), q) or torch.allclose(
            quantise_tensor("sh_dc", q, "8bit"), q, rtol=1e-6, atol=0)   # stored values stay where they are
    model = trained_looking("2dgs", n=200)
    ranges = {k: v.numel() // v.shape[0] for k, v in model.state_dict().items()
              if encoding_for(k, v, "8bit") == "u8h"}
    assert set(ranges) == {"log_scales", "quats", "logit_opacity", "sh_dc"}

    def payload(data):  # the bytes after the header
        return len(data) - 8 - struct.unpack_from("<I", data, 4)[0]

    with_half = payload(pack_checkpoint(model.checkpoint(), "8bit"))
    with pytest.MonkeyPatch.context() as m:
        m.setattr(packing, "_half_ranges", lambda array, bits: None)
        assert payload(pack_checkpoint(model.checkpoint(), "8bit")) - with_half == 4 * sum(ranges.values())


def test_a_value_beyond_the_half_float_range_is_stored_as_it_is(tmp_path):
    """At float16 a tensor holding a value a half float cannot (65504 and beyond) is stored at full precision, not
    as infinity; the others are still half floats, and the file's size says so."""
    model = trained_looking("2dgs")
    name, param = next((k, p) for k, p in model.named_parameters() if k != "means")
    with torch.no_grad():
        param.view(-1)[0] = 7e4
    model.precision = "float16"
    path = tmp_path / "m.szp"
    save_model(model, path)
    back = load_model(path).state_dict()
    assert torch.equal(back[name], model.state_dict()[name]) and torch.isfinite(back[name]).all()
    others = [k for k in back if k not in (name, "means") and back[k].is_floating_point()]
    assert others and all(torch.equal(back[k], model.state_dict()[k].half().float()) for k in others)
    assert path.stat().st_size == stored_bytes(model, "float16")


def test_a_budget_is_refused_for_primitives_that_store_nothing(monkeypatch):
    from splatzoo.zoo import plain_fit_count, plain_model

    monkeypatch.setattr(type(plain_model("2dgs", 1)), "stored_row_bytes",
                        lambda self, precision: torch.zeros(self.num_primitives))
    with pytest.raises(SplatzooError, match="--num-primitives"):
        plain_fit_count("2dgs", 1_000_000, "8bit")


def test_training_through_stored_values_restores_and_differentiates():
    model = trained_looking("gabor")
    before = {k: v.clone() for k, v in model.state_dict().items()}
    stored = stored_copy(model, "8bit")
    with stored_values(model, "8bit"):
        for k, v in stored.state_dict().items():
            assert torch.equal(model.state_dict()[k], v), k
        loss = sum((p ** 2).sum() for p in model.parameters())
        loss.backward()
    for k, v in before.items():
        assert torch.equal(model.state_dict()[k], v), k   # the full-precision values are back ...
    for name, p in model.named_parameters():   # ... with the gradient taken at the stored ones (straight through)
        assert torch.allclose(p.grad, 2 * dict(stored.named_parameters())[name].detach()), name


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name", ["2dgs", "gabor", "neural-gabor", "textured", "beta-gabor"])
def test_budget_count_never_exceeds_the_budget(name, precision):
    choice = ModelChoice(name, name)
    for budget in (3_000, 20_000, 104_000):
        n = budget_count(choice, budget, precision)
        assert n >= 1
        assert stored_cost(choice, n, precision) <= budget < stored_cost(choice, n + 1, precision)
    assert budget_count(choice, 10, precision) == 0


def test_a_large_budget_is_fitted_without_building_a_model_that_large():
    from splatzoo.zoo import EXACT_FIT_UP_TO, plain_fit_count, plain_stored_bytes

    one = plain_stored_bytes("2dgs", 1, "8bit")
    budget = 200_000_000  # twelve million 8-bit 2dgs rows: estimated from the cost of a row, not settled by building
    n = plain_fit_count("2dgs", budget, "8bit")
    assert n > EXACT_FIT_UP_TO and abs(n - (1 + (budget - one) / 16)) <= 2  # the header writes more digits
    # beta-gabor's plain row stores a bit of wave count: a fraction of a byte that the estimate keeps
    one = plain_stored_bytes("beta-gabor", 1, "8bit")
    n = budget_count(ModelChoice("beta-gabor", "beta-gabor"), budget, "8bit")
    assert abs(n - (1 + (budget - one) / 17.125)) <= 2


def test_parse_budgets():
    assert parse_budgets("5%,25%, 100%") == [("5%", "fraction", 0.05), ("25%", "fraction", 0.25),
                                             ("100%", "fraction", 1.0)]
    assert parse_budgets("200kB,1.5MB,120000,2KiB") == [("200kB", "bytes", 200e3), ("1.5MB", "bytes", 1.5e6),
                                                        ("120000", "bytes", 120000.0), ("2KiB", "bytes", 2048.0)]
    assert parse_budgets([0.25, 5000]) == [("25%", "fraction", 0.25), ("5000B", "bytes", 5000.0)]
    for bad, message in (("5%,x", "'x' is not a budget"), ("0%", "positive"), ("-5%", "not a budget"),
                         ("5%,5%", "each budget once"), ("", "at least one"), ("1e999MB", "positive")):
        with pytest.raises(SplatzooError, match=message):
            parse_budgets(bad)


# --- damaged and crafted packed files ----------------------------------------------------------------------------

def _packed(name="gabor"):
    return pack_checkpoint(trained_looking(name).checkpoint(), "8bit")


def _with_header(data: bytes, edit, zdict: bytes | None = None) -> bytes:
    """The packed file with its header edited, written back with the preset dictionary `zdict` (None: without one,
    as version 1 was)."""
    (length,) = struct.unpack_from("<I", data, 4)
    header = read_header(data)
    edit(header)
    deflate = zlib.compressobj(9, zdict=zdict) if zdict else zlib.compressobj(9)
    text = deflate.compress(json.dumps(header).encode()) + deflate.flush()
    return data[:4] + struct.pack("<I", len(text)) + text + data[8 + length:]


def _as_version(version: int):
    """An edit that writes a version-3 header as `version` wrote it: each tensor's shape in its entry."""
    def edit(header):
        for entry, rows in zip(header["tensors"], header.pop("rows")):
            entry["shape"] = [] if rows is None else [rows, *entry.pop("columns")]
            entry.pop("columns", None)
        header["version"] = version
    return edit


def test_the_header_dictionaries_never_change():
    """Every file needs the very dictionary it was written with (zlib checks its Adler-32)."""
    assert hashlib.sha256(header_dictionary(2)).hexdigest() == "a97165705b37cbd27d19f4c19210181fb1c876a0d6cdaa5981adf11a204ce6f9"
    assert hashlib.sha256(header_dictionary(3)).hexdigest() == "f2df5487ec80a106fdd7367bb062b7a7cdafa400100bba536f1e79001932cd9c"
    assert header_dictionary() == header_dictionary(packing.VERSION)


@pytest.mark.parametrize("name", ["2dgs", "beta-gabor"])
def test_headers_are_small_and_version_1_and_2_files_still_load(name, tmp_path, monkeypatch):
    """A small budget's file spends on surfels what its header does not take: a beta-gabor header of 40 surfels
    takes under 60 bytes, a 2dgs one under 40. Files written by versions 1 and 2 (8-bit ranges always float32)
    load as they did."""
    model = trained_looking(name, n=40)
    model.precision = "8bit"
    data = pack_checkpoint(model.checkpoint(), "8bit")
    (length,) = struct.unpack_from("<I", data, 4)
    assert length < {"2dgs": 40, "beta-gabor": 60}[name]
    assert len(zlib.compress(json.dumps(read_header(data), separators=(",", ":")).encode(), 9)) > 4 * length
    monkeypatch.setattr(packing, "_half_ranges", lambda array, bits: None)  # as versions 1 and 2 stored ranges
    older = pack_checkpoint(model.checkpoint(), "8bit")
    files = {"v3": data, "v2": _with_header(older, _as_version(2), header_dictionary(2)),
             "v1": _with_header(older, _as_version(1))}
    loaded = {}
    for version, content in files.items():
        (tmp_path / f"{version}.szp").write_bytes(content)
        loaded[version] = load_model(tmp_path / f"{version}.szp").state_dict()
    for k, v in model.state_dict().items():
        for version in ("v1", "v2"):
            assert torch.equal(loaded[version][k], loaded["v1"][k]), k
        step = (v.max() - v.min()) / 255 if v.is_floating_point() and v.numel() else 0
        assert torch.allclose(loaded["v3"][k], loaded["v1"][k], rtol=0, atol=float(step) + 1e-6), k


BOMB = zlib.compress(b" " * 2**25, 9)   # a 32 MB header in 32 kB


@pytest.mark.parametrize("damage,message", [
    (lambda d: d[:3], "no SZPK header"),
    (lambda d: b"XXXX" + d[4:], "no SZPK header"),
    (lambda d: d[:4] + struct.pack("<I", 10**9) + d[8:], "header claims"),
    (lambda d: d[:4] + struct.pack("<I", 4) + b"{{{{" + d[12:], "not valid compressed JSON"),
    (lambda d: d[:4] + struct.pack("<I", len(BOMB)) + BOMB + d[8:], "at most 16777216 bytes"),
    (lambda d: d[:-5], "truncated"),
    (lambda d: d + b"extra", "5 bytes follow the last tensor"),
    (lambda d: _with_header(d, lambda h: h.update(version=99)), "format version 99"),
    (lambda d: _with_header(d, lambda h: h.update(precision="4bit")), "unknown precision"),
    (lambda d: _with_header(d, lambda h: h["tensors"][0].update(columns=[2**39])), "invalid shape|truncated"),
    (lambda d: _with_header(d, lambda h: h["rows"].__setitem__(0, -1)), "invalid shape"),
    (lambda d: _with_header(d, lambda h: h["rows"].__setitem__(0, None)), "invalid shape"),
    (lambda d: _with_header(d, lambda h: h["tensors"][0].pop("columns")), "invalid shape"),
    (lambda d: _with_header(d, lambda h: h["rows"].pop()), "one row count per tensor"),
    (lambda d: _with_header(d, lambda h: h.pop("rows")), "one row count per tensor"),
    (lambda d: d[:8] + d[8:10] + b"\x00\x00\x00\x01" + d[14:], "dictionary this splatzoo does not have"),
    (lambda d: _with_header(d, lambda h: h["tensors"][0].update(dtype="object")), "unknown dtype"),
    (lambda d: _with_header(d, lambda h: h["tensors"][0].update(encoding="zip")), "unknown encoding"),
    (lambda d: _with_header(d, lambda h: (h["tensors"].append(h["tensors"][0]), h["rows"].append(h["rows"][0]))),
     "appears twice"),
    (lambda d: _with_header(d, lambda h: h.update(tensors="all")), "lists no tensors"),
    (lambda d: _with_header(d, lambda h: h.update(model="nonexistent")), "nonexistent"),
    (lambda d: _with_header(d, lambda h: h["config"].update(n_waves=-3)), "n_waves"),
])
def test_damaged_packed_files_are_named_errors(tmp_path, damage, message):
    path = tmp_path / "bad.szp"
    path.write_bytes(damage(_packed()))
    with pytest.raises(SplatzooError, match=message) as e:
        load_model(path)
    assert "bad.szp" in str(e.value)


def test_non_finite_values_in_a_packed_file_are_refused(tmp_path):
    model = trained_looking("2dgs")
    ck = model.checkpoint()
    data = bytearray(pack_checkpoint(ck, "float32"))
    (length,) = struct.unpack_from("<I", data, 4)
    struct.pack_into("<f", data, 8 + length, float("nan"))   # the first value of the first tensor (means)
    path = tmp_path / "nan.szp"
    path.write_bytes(bytes(data))
    with pytest.raises(SplatzooError, match="means has 1 non-finite"):
        load_model(path)
    assert unpack_checkpoint(pack_checkpoint(ck, "8bit"))["precision"] == "8bit"


def test_a_run_trained_with_store_8bit(tmp_path):
    """The run's model.pt and model.szp hold the same stored values; its metrics give both sizes, the stored one
    that of model.szp, and the full-precision PSNR beside it; eval reads the .szp file."""
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "data", views=6, width=32, height=32)
    run = tmp_path / "run"
    res = CliRunner().invoke(app, ["train", str(data), "--model", "gabor", "-i", "30", "--no-densify", "-n", "300",
                                   "--store", "8bit", "--out", str(run)])
    assert res.exit_code == 0, res.output
    assert "stored as 8bit" in res.output
    pt, szp = load_model(run / "model.pt"), load_model(run / "model.szp")
    assert pt.precision == szp.precision == "8bit"
    for k, v in pt.state_dict().items():
        assert torch.allclose(szp.state_dict()[k], v, rtol=1e-6, atol=1e-6), k
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["stored_bytes"] == (run / "model.szp").stat().st_size
    assert metrics["precision"] == "8bit" and metrics["size_bytes"] > 3 * metrics["stored_bytes"]
    assert np.isfinite(metrics["float32_psnr"]) and abs(metrics["float32_psnr"] - metrics["psnr"]) < 1.0
    res = CliRunner().invoke(app, ["eval", str(run / "model.szp"), "--data", str(data)])
    assert res.exit_code == 0, res.output
    from splatzoo.runs import Run
    Run(run).clear()   # what --overwrite removes: the packed file too
    assert not (run / "model.szp").exists() and not (run / "model.pt").exists()
    res = CliRunner().invoke(app, ["train", str(data), "--store", "4bit", "--out", str(tmp_path / "r2")])
    assert res.exit_code != 0 and "--store must be one of float32, float16, 8bit" in str(res.exception)
    assert not (tmp_path / "r2").exists()


def test_compare_budgets_trains_every_model_at_every_budget(tmp_path):
    from splatzoo.compare import compare
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "data", views=6, width=32, height=32)
    out = tmp_path / "cmp"
    report = compare(["2dgs", "gabor"], data, out, iterations=20, num_primitives=600, budgets="25%,100%",
                     store="8bit", progress=False, budget_start=1)
    rate = report["rate"]
    assert [(r["model"], r["budget"]) for r in rate] == [("2dgs", "25%"), ("gabor", "25%"), ("2dgs", "100%"),
                                                         ("gabor", "100%")]
    reference = report["runs"]["2dgs"]["stored_bytes"]
    for r in rate:
        assert r["stored_bytes"] <= r["budget_bytes"], r
        assert r["stored_bytes"] == (out / "runs" / r["run"] / "model.szp").stat().st_size
    assert rate[2]["run"] == "2dgs" and rate[2]["stored_bytes"] == reference   # the reference run, reused
    assert rate[3]["num_primitives"] < rate[2]["num_primitives"]               # a gabor surfel costs more
    assert (out / "rate.png").stat().st_size > 0 and "Rate: every model at every budget" in (
        out / "report.md").read_text()
    with pytest.raises(SplatzooError, match="holds no primitive"):   # refused before the reference run trains
        compare(["2dgs"], data, tmp_path / "small", iterations=20, num_primitives=600, budgets="10B", store="8bit",
                progress=False)
    assert not (tmp_path / "small" / "runs").exists()
    with pytest.raises(SplatzooError, match="holds no primitive"):   # a fraction too: before any run is retrained
        compare(["2dgs"], data, tmp_path / "small", iterations=20, num_primitives=600, budgets="0.01%",
                store="8bit", progress=False, overwrite=True)
    assert not (tmp_path / "small" / "runs").exists()
    with pytest.raises(SplatzooError, match="give one of them"):
        compare(["2dgs"], data, out, iterations=20, budgets="5%", equal_bytes=True, progress=False)


def test_budgeted_runs_start_with_each_members_multiple_of_what_fits_and_shed_to_the_budget(tmp_path):
    from splatzoo.compare import compare
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "data", views=6, width=32, height=32)
    out = tmp_path / "cmp"
    report = compare(["2dgs", "beta-gabor"], data, out, iterations=40, num_primitives=300, budgets="30%,100%",
                     store="8bit", progress=False)
    assert report["settings"]["budget_start"] is None  # each member's own (SplatModel.budget_start)
    for r in report["rate"]:
        fit = r["fit_primitives"]
        start = {"2dgs": 3, "beta-gabor": min(3, 1 + 18 / fit ** 0.5)}[r["model"]]  # plain surfels: 3x at any budget
        assert r["start_primitives"] == math.ceil(start * fit), r
        assert r["stored_bytes"] <= r["budget_bytes"], r     # shed down to the budget
        assert r["num_primitives"] <= r["fit_primitives"], r
        assert r["run"] != r["model"]                        # 100% is a run of its own, not the unbudgeted one
        assert r["stored_bytes"] == (out / "runs" / r["run"] / "model.szp").stat().st_size
    fits = [r["fit_primitives"] for r in report["rate"] if r["model"] == "beta-gabor"]
    told = " / ".join(f"{math.ceil(min(3, 1 + 18 / fit ** 0.5) * fit) / fit:.2g}x" for fit in fits)
    assert f"each run started with 3x (2dgs), {told} by budget (beta-gabor) the primitives that fit" in (
        out / "report.md").read_text()
    for bad in (0.5, float("nan"), 17):
        with pytest.raises(SplatzooError, match="--budget-start must be a number from 1 to 16"):
            compare(["2dgs"], data, tmp_path / "bad", iterations=20, budgets="50%", budget_start=bad, progress=False)
        assert not (tmp_path / "bad").exists()


def test_the_rate_table_says_each_members_start_and_reads_an_older_reports_single_start():
    from splatzoo.compare import rate_markdown

    rate = [{"model": m, "budget": "5%", "budget_bytes": 1608, "psnr": p, "lpips": 0.5, "stored_bytes": 1600,
             "num_primitives": 90}
            for m, p in (("2dgs", 21.0), ("beta-gabor", 22.0))]
    text = "\n".join(rate_markdown(rate, "8bit", {"2dgs": 3.0, "beta-gabor": 2.0}))
    assert "each run started with 3x (2dgs), 2x (beta-gabor) the primitives that fit" in text
    assert "each run started with 2x the primitives that fit" in "\n".join(rate_markdown(rate, "8bit", 2.0))
    assert "started with" not in "\n".join(rate_markdown(rate, "8bit", 1.0)) + "\n".join(rate_markdown(rate, "8bit"))
    assert "**22.00**" in text
    # records that carry their counts say each member's start at each budget, whatever the settings say
    rate += [{**r, "budget": "100%", "budget_bytes": 32178} for r in rate]
    for r, (fit, start) in zip(rate, ((100, 300), (80, 240), (2000, 6000), (1864, 2642))):
        r.update(fit_primitives=fit, start_primitives=start)
    text = "\n".join(rate_markdown(rate, "8bit", None))
    assert "each run started with 3x (2dgs), 3x / 1.4x by budget (beta-gabor) the primitives that fit" in text


# --- a byte budget -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["2dgs", "gabor-adaptive", "beta-gabor", "textured", "neural-gabor"])
@pytest.mark.parametrize("precision", ["float32", "8bit"])
def test_stored_row_bytes_add_up_to_the_file(name, precision):
    """Each primitive's rows, summed, are the packed file less what does not grow with the count (header, column
    ranges): within 2% of the file at 400 surfels."""
    model = trained_looking(name, n=400)
    rows = float(model.stored_row_bytes(precision).sum())
    empty = stored_bytes(trained_looking(name, n=400).shed_richness(), precision) - float(
        trained_looking(name, n=400).shed_richness().stored_row_bytes(precision).sum())
    assert abs(stored_bytes(model, precision) - (rows + empty)) <= 0.02 * stored_bytes(model, precision)


def _probe_for(model, cams, targets):
    def probe(surfels_of):
        return sum(float(((model.render(c, surfels=surfels_of(c), image_only=True).rgb - t) ** 2).mean())
                   for c, t in zip(cams, targets)) / len(cams)
    return probe


def _ring_cameras(n=4, size=32):
    from splatzoo import Camera
    return [Camera.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0], up=(0, 0, 1), width=size, height=size)
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def test_the_budget_sheds_what_costs_the_views_least():
    """Waves with no amplitude go before surfels; surfels nobody sees go before waves that draw stripes."""
    from splatzoo.training import budget

    cams = _ring_cameras()
    model = trained_looking("gabor-adaptive", n=300, seed=1)
    with torch.no_grad():
        model.logit_opacity.fill_(3.0)
        model.log_scales.fill_(-2.0)
        model.color_diff.fill_(0.0)   # every wave invisible
    targets = [model.render(c, image_only=True).rgb for c in cams]
    size = stored_bytes(model, "8bit")
    out = budget.enforce(model, None, _probe_for(model, cams, targets), size - 2000, "8bit", share=1.0)
    assert out["stored_bytes"] <= size - 2000 and all("waves" in w for w in out["shed"]), out
    assert model.num_primitives == 300

    model = trained_looking("gabor-adaptive", n=300, seed=1)
    with torch.no_grad():
        model.logit_opacity.fill_(3.0)
        model.log_scales.fill_(-1.0)
        model.wave_weights.fill_(0.3)   # every wave draws stripes: even the faintest cost the views something
        model.wave_freqs.fill_(0.3)
        model.color_diff.fill_(0.5)
        model.logit_opacity[:150] = -9.0   # half the surfels all but transparent
    waves_seen = int(model.active_slots()[150:].sum())
    targets = [model.render(c, image_only=True).rgb for c in cams]
    size = stored_bytes(model, "8bit")
    out = budget.enforce(model, None, _probe_for(model, cams, targets), size - 2000, "8bit", share=1.0)
    seen = torch.sigmoid(model.logit_opacity) > 0.5
    assert out["stored_bytes"] <= size - 2000 and any("surfels" in w for w in out["shed"]), out
    assert model.num_primitives < 300 and int(seen.sum()) == 150      # every surfel that is seen stays,
    assert int(model.active_slots()[seen].sum()) == waves_seen, out   # with its waves (the waves shed were unseen)


def test_a_shedding_chooses_a_quarter_of_its_excess_at_a_time(monkeypatch):
    """Each choice frees at most a quarter of the shedding's excess, so one shedding can take some waves and some
    surfels (one choice for the whole cut took it all in one kind)."""
    from splatzoo.models.base import Shedding
    from splatzoo.training import budget

    class Net:   # frees exactly what it is asked; waves cheap at first, dearer each time (error 0.5 + 2k; surfels 1 + k)
        size, asked, taken = 10_000, [], {"waves": 0, "surfels": 0}

        def shed_free(self, optimizer):
            return None

        def shedding_options(self, nbytes, precision, optimizer=None):
            self.asked.append(nbytes)

            def take(kind):
                self.size -= nbytes
                self.taken[kind] += 1
            return [Shedding(kind, kind, lambda kind=kind: take(kind)) for kind in ("surfels", "waves")]

    net = Net()
    monkeypatch.setattr(budget, "stored_bytes", lambda n, precision: n.size)
    error = {"waves": lambda: 0.5 + 2 * net.taken["waves"], "surfels": lambda: 1.0 + net.taken["surfels"]}
    out = budget.enforce(net, None, lambda preview: error[preview](), 6_000, "8bit", share=1.0)
    assert out["stored_bytes"] <= 6_000 and max(net.asked) <= 1_000, (out, net.asked)
    assert out["shed"] == ["waves", "surfels", "surfels", "waves"], out


def test_budget_share_meets_the_budget_at_until():
    from splatzoo.training import budget

    steps = budget.shedding_steps(1500)
    assert steps[0] == 750 and steps[-1] == 1500 and steps[-2] == round(0.85 * 1500)
    excess = 1.0
    for s in steps:
        excess *= 1 - budget.share_due(s, 1500)
    assert excess == 0.0


def test_a_run_within_a_byte_budget_ends_within_it_and_resumes(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    data = make_synthetic_scene("sweater", tmp_path / "data", views=6, width=32, height=32)
    choice = ModelChoice("gabor-adaptive", "gabor-adaptive")
    budget_bytes = 6000
    count = budget_count(choice, budget_bytes, "8bit")
    assert count > budget_count(ModelChoice("gabor", "gabor", {"n_waves": 8}), budget_bytes, "8bit")
    cfg = TrainConfig(iterations=40, densify=False, num_primitives=count, max_bytes=budget_bytes, store="8bit",
                      seed=3)
    whole = train(data, "gabor-adaptive", {}, cfg, tmp_path / "whole", progress=False)
    assert whole.metrics["stored_bytes"] <= budget_bytes
    assert (tmp_path / "whole" / "model.szp").stat().st_size == whole.metrics["stored_bytes"]
    train(data, "gabor-adaptive", {}, cfg, tmp_path / "cut", progress=False, stop_after=27)  # between sheddings
    resumed = train(data, None, None, None, tmp_path / "cut", resume=True, progress=False)
    assert resumed.metrics["stored_bytes"] <= budget_bytes
    assert resumed.model.num_primitives == whole.model.num_primitives


def test_a_byte_budget_that_holds_no_surfel_or_is_no_size_is_refused_before_the_run(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "data", views=4, width=32, height=32)
    from splatzoo.models.base import RenderSettings
    from splatzoo.zoo import plain_stored_bytes

    # the file of one plain surfel, with the render settings the run records (anti-aliased, over black or None)
    one = max(plain_stored_bytes("beta-gabor", 1, "8bit", RenderSettings(True, bg)) for bg in (None, (0.0, 0.0, 0.0)))
    assert one > stored_cost(ModelChoice("beta-gabor", "beta-gabor"), 1, "8bit")  # the settings take header bytes
    for size, message in ((str(one - 1), f"--max-bytes {one - 1:,} holds no beta-gabor surfel: the file of one costs "
                                         f"{one:,} bytes stored as 8bit; give a larger budget"),
                          ("5%", "--max-bytes: '5%' is not a size; give one such as 200kB"),
                          ("0", "--max-bytes: '0' must be at least 1 byte"), ("nan", "is not a size")):
        out = tmp_path / f"r{size}"
        res = CliRunner().invoke(app, ["train", str(data), "--model", "beta-gabor", "-i", "4", "--store", "8bit",
                                       "--max-bytes", size, "--out", str(out)])
        assert res.exit_code != 0 and message in str(res.exception), (size, res.output, res.exception)
        assert not out.exists()
    res = CliRunner().invoke(app, ["train", str(data), "--model", "beta-gabor", "-i", "4", "--store", "8bit",
                                   "--no-densify", "-n", "5", "--max-bytes", str(one), "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "r" / "model.szp").stat().st_size <= one


def test_densification_grows_to_the_members_multiple_of_what_the_byte_budget_holds(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.data import load_scene
    from splatzoo.training import TrainConfig, Trainer, budget

    scene = load_scene(make_synthetic_scene("sweater", tmp_path / "data", views=4, width=32, height=32))
    # 8-bit rows: 2DGS's 16 bytes; beta-gabor's plain surfel adds its falloff and one bit of wave count
    for name, per in (("2dgs", 16), ("beta-gabor", 17.125)):
        cfg = TrainConfig(iterations=10, num_primitives=60, max_bytes=600, store="8bit")
        trainer = Trainer.start(scene, name, make_config(name), cfg, "cpu", torch.device("cpu"))
        fit = int(600 // per)
        start = {"2dgs": 3, "beta-gabor": min(3, 1 + 18 / fit ** 0.5)}[name]  # its own, as compare's runs start
        assert trainer.net.budget_start(fit) == start and budget.start_count(trainer.net, 600, "8bit") == trainer.budget
        assert trainer.budget == math.ceil(start * fit) < Trainer.start(scene, name, make_config(name), TrainConfig(
            iterations=10, num_primitives=60), "cpu", torch.device("cpu")).budget, name


def test_beta_gabors_budgeted_start_falls_as_the_budget_grows_and_plain_surfels_keep_theirs():
    from splatzoo.registry import MODELS

    bg, plain = MODELS.get("beta-gabor").cls, MODELS.get("2dgs").cls
    starts = [bg.budget_start(fit) for fit in (1, 36, 80, 455, 1864, 10**6)]
    assert starts[:2] == [3.0, 3.0]                       # never more than three times what fits
    assert starts == sorted(starts, reverse=True) and all(1 < s <= 3 for s in starts)
    assert [round(s, 1) for s in starts[2:5]] == [3.0, 1.8, 1.4]
    assert {plain.budget_start(fit) for fit in (1, 80, 10**6)} == {3.0}
    assert MODELS.get("textured").cls.budget_start(80) == MODELS.get("gabor").cls.budget_start(80) == 2.0


def test_a_budgeted_run_starts_from_its_multiple_of_what_fits_unless_told_a_count(tmp_path, capsys):
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.data import load_scene
    from splatzoo.training import TrainConfig, Trainer

    scene = load_scene(make_synthetic_scene("sweater", tmp_path / "data", views=4, width=32, height=32))
    points = scene.points.shape[0]
    cpu = torch.device("cpu")
    for name, per, times in (("2dgs", 16, 3), ("beta-gabor", 17.125, 3)):  # beta-gabor: 3x at 35 surfels that fit
        start = times * int(600 // per)
        assert points > start
        trainer = Trainer.start(scene, name, make_config(name), TrainConfig(iterations=10, max_bytes=600, store="8bit"),
                                "cpu", cpu)
        assert trainer.net.num_primitives == start == trainer.budget, name  # as compare --budgets starts its runs
        assert (f"--max-bytes 600: starting from {start:,} of the scene's {points:,} points (3x the {name} surfels"
                in capsys.readouterr().out)
        told = Trainer.start(scene, name, make_config(name), TrainConfig(
            iterations=10, num_primitives=points, max_bytes=600, store="8bit"), "cpu", cpu)
        assert told.net.num_primitives == points  # --num-primitives is kept: the run sheds from there
        roomy = Trainer.start(scene, name, make_config(name), TrainConfig(iterations=10, max_bytes=10**7, store="8bit"),
                              "cpu", cpu)
        assert roomy.net.num_primitives == points and capsys.readouterr().out == ""
