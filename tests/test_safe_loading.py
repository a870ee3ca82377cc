"""Model files and PLY files are read safely: a crafted or damaged file is a SplatzooError that names the file and
what is wrong, never code execution, a memory bomb or a traceback from deep inside torch or numpy."""
import json
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from torch import nn
from typer.testing import CliRunner

import splatzoo
from splatzoo import ModelSpec, Surfels, create_model, load_model, save_model
from splatzoo.cli import app
from splatzoo.errors import SplatzooError, UnknownNameError
from splatzoo.export import export_run, read_ply_vertices, save_ply
from splatzoo.models.base import ModelOptionError, SurfelModel
from splatzoo.zoo import make_config, model_from_checkpoint


def small_model(name="gabor", n=12, **options):
    g = torch.Generator().manual_seed(0)
    return create_model(name, torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), **options)


class Payload:
    """Unpickling this calls Path.touch(marker): what a malicious model file would do with os.system instead."""

    def __init__(self, marker):
        self.marker = Path(marker)

    def __reduce__(self):
        return (Path.touch, (self.marker,))


# --- model files ------------------------------------------------------------------------------------------------

def test_payload_would_run_without_weights_only(tmp_path):
    """The check below is only meaningful if the payload really runs when unpickled without weights_only."""
    marker = tmp_path / "control"
    torch.save({"x": Payload(marker)}, tmp_path / "evil.pt")
    torch.load(tmp_path / "evil.pt", weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("shape", ["model", "training checkpoint"])
def test_crafted_pickle_is_refused_and_runs_nothing(tmp_path, shape):
    marker = tmp_path / "pwned"
    ckpt = small_model().checkpoint()
    ckpt["state"]["means"] = Payload(marker)
    if shape == "training checkpoint":
        ckpt = {"model": ckpt, "iteration": 3, "optimizer": {}}
    path = tmp_path / "model.pt"
    torch.save(ckpt, path)
    with pytest.raises(SplatzooError,
                       match=r"model file .*model\.pt.*cannot be read safely.*\.pt or \.szp file written by") as e:
        load_model(path)
    assert not marker.exists()
    # the refusal says why, and never passes on torch's advice to load it with weights_only=False
    assert "could run code from the file" in str(e.value) and "weights_only" not in str(e.value)


def test_empty_and_truncated_model_files(tmp_path):
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(SplatzooError, match=r"empty\.pt is empty"):
        load_model(empty)
    good = tmp_path / "good.pt"
    save_model(small_model(), good)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(SplatzooError, match=r"cut\.pt"):
        load_model(cut)
    with pytest.raises(SplatzooError, match=r"missing\.pt does not exist"):
        load_model(tmp_path / "missing.pt")


def test_good_model_and_training_checkpoint_still_load(tmp_path):
    model = small_model(n_waves=3, prune_waves=0.02)
    with torch.no_grad():
        model.wave_weights.mul_(torch.rand(model.wave_weights.shape, generator=torch.Generator().manual_seed(1)) * 3)
    assert model.prune_waves(0.003)["removed"] > 0   # the packed checkpoint layout
    save_model(model, tmp_path / "model.pt")
    torch.save({"model": model.checkpoint(), "iteration": 7}, tmp_path / "checkpoint.pt")
    for name in ("model.pt", "checkpoint.pt"):
        back = load_model(tmp_path / name)
        for k, v in model.state_dict().items():
            assert torch.equal(v, back.state_dict()[k]), (name, k)
        assert torch.equal(back.wave_counts, model.wave_counts)


def _damaged(tmp_path, edit):
    ckpt = small_model().checkpoint()
    edit(ckpt)
    path = tmp_path / "model.pt"
    torch.save(ckpt, path)
    return path


@pytest.mark.parametrize("edit,message", [
    (lambda c: c["config"].update(n_wave=3), r"option\(s\) 'n_wave'.*its options: .*n_waves"),
    (lambda c: c["config"].update(n_waves="4"), r"n_waves .* must be int, got '4'"),
    (lambda c: c["state"].pop("wave_freqs"), r"lacks parameter\(s\) wave_freqs"),
    (lambda c: c["state"].update(bonus=torch.zeros(12)), r"unexpected bonus"),
    (lambda c: c["config"].update(sh_degree=1), r"lacks parameter\(s\) sh_rest"),
    (lambda c: c["state"]["means"].__setitem__((3, 1), float("nan")), r"means has 1 non-finite \(NaN or inf\)"),
    (lambda c: c["state"]["color_base"].__setitem__((0, 0), float("inf")), r"color_base has 1 non-finite"),
    (lambda c: c["state"].update(means=torch.zeros(11, 3)), r"disagree on the number of primitives.*means: 11"),
    (lambda c: c["state"].update(quats=torch.zeros(12, 3)), r"quats has shape \[12, 3\].*expects \[N, 4\]"),
    (lambda c: c["state"].update(means=torch.zeros(12, 3, dtype=torch.int32)), r"means holds torch.int32"),
    (lambda c: c["state"].update(means=[0.0, 1.0]), r"'means' is a list, not a dense tensor"),
    (lambda c: c.pop("state"), r"no 'state' entry"),
])
def test_damaged_checkpoints_say_what_is_wrong(tmp_path, edit, message):
    path = _damaged(tmp_path, edit)
    with pytest.raises(SplatzooError, match=message) as info:
        load_model(path)
    assert str(path) in str(info.value) and "written by splatzoo" in str(info.value)


def test_packed_checkpoints_refuse_unknown_entries(tmp_path):
    """An adaptive model's checkpoint (active waves packed) is checked by its own loader, but an entry neither
    layout has is still refused."""
    ckpt = small_model(prune_relative=2).checkpoint()
    assert "wave_mask" in ckpt["state"]
    ckpt["state"]["bonus"] = torch.zeros(12)
    with pytest.raises(SplatzooError, match="unexpected bonus"):
        model_from_checkpoint(ckpt)


def test_unknown_model_name_in_checkpoint(tmp_path):
    path = _damaged(tmp_path, lambda c: c.update(model="gabr"))
    with pytest.raises(UnknownNameError, match=r"model\.pt.*unknown model 'gabr'.*Did you mean 'gabor'"):
        load_model(path)


def test_model_from_checkpoint_checks_what_resume_passes_it():
    ckpt = small_model().checkpoint()
    ckpt["state"]["wave_phases"] = ckpt["state"]["wave_phases"][:, :2]
    with pytest.raises(SplatzooError, match=r"wave_phases has shape \[12, 2\].*\[N, 4\]"):
        model_from_checkpoint(ckpt)
    with pytest.raises(SplatzooError, match="expected a splatzoo model"):
        model_from_checkpoint([1, 2])


# --- model options ----------------------------------------------------------------------------------------------

@dataclass
class _WideConfig:
    width: int = 2
    gain: float = 1.0
    tinted: bool = True


class _WideModel(SurfelModel):
    """A plugin-like model whose parameter width comes from its config, with a bool option."""

    def __init__(self, config, num_primitives=0):
        super().__init__(config, num_primitives)
        self.extra = nn.Parameter(torch.zeros(num_primitives, config.width))

    def init_from_points(self, points, colors, generator):
        self.init_geometry(points, generator)

    def surfels(self, camera):
        g = self.geometry()
        return Surfels.constant_color(g["means"], g["quats"], g["scales"], g["opacities"],
                                      self.means.new_full(self.means.shape, 0.5))


@pytest.fixture
def wide_model():
    from splatzoo.registry import MODELS, register_model

    register_model(ModelSpec("safe-test-wide", _WideModel, _WideConfig, "test"))
    yield "safe-test-wide"
    MODELS._entries.pop("safe-test-wide", None)


@pytest.mark.parametrize("text,value", [("False", False), ("false", False), ("0", False), ("no", False),
                                        ("OFF", False), ("True", True), ("yes", True), ("1", True), ("on", True),
                                        (False, False), (True, True)])
def test_bool_options_are_parsed_not_cast(wide_model, text, value):
    assert make_config(wide_model, tinted=text).tinted is value


@pytest.mark.parametrize("options,message", [
    ({"tinted": "maybe"}, r"option tinted expects bool .*got 'maybe'"),
    ({"tinted": 2}, r"option tinted expects bool"),
    ({"gain": "nan"}, r"option gain expects a finite float, got 'nan'"),
    ({"gain": "inf"}, r"option gain expects a finite float"),
    ({"gain": "fast"}, r"option gain expects float, got 'fast'"),
    ({"width": "2.5"}, r"option width expects int, got '2.5'"),
    ({"width": 2.5}, r"option width expects int, got 2.5"),
    ({"width": True}, r"option width expects int, got True"),
])
def test_bad_option_values_name_option_type_and_value(wide_model, options, message):
    with pytest.raises(ModelOptionError, match=message):
        make_config(wide_model, **options)


def test_strings_convert_by_field_type(wide_model):
    cfg = make_config(wide_model, width="3", gain="0.5")
    assert cfg.width == 3 and cfg.gain == 0.5
    assert make_config("gabor", prune_waves="0.01", n_waves="2").prune_waves == 0.01


# --- PLY files --------------------------------------------------------------------------------------------------

PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
         "rot_0", "rot_1", "rot_2", "rot_3"]
ROW = "0 0 0 0 0 0 0 0 0 1 0 0 0"


def ascii_ply(count, rows, props=PROPS, comments=()):
    header = ["ply", "format ascii 1.0", *[f"comment {c}" for c in comments], f"element vertex {count}",
              *[f"property float {p}" for p in props], "end_header"]
    return ("\n".join(header + rows) + "\n").encode()


def test_ascii_count_bomb_fails_fast_with_little_memory(tmp_path):
    path = tmp_path / "bomb.ply"
    path.write_bytes(ascii_ply(30_000_000, [ROW] * 2))
    assert path.stat().st_size < 400
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(SplatzooError, match=r"bomb\.ply.*promises 30000000 vertices.*Export the model again"):
            splatzoo.load_ply(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - start < 1.0
    assert peak < 5_000_000


@pytest.mark.parametrize("count", ["-1", "3.5", "abc", "", "1e3"])
def test_element_counts_must_be_whole_non_negative_numbers(tmp_path, count):
    path = tmp_path / "count.ply"
    path.write_bytes(ascii_ply(count, [ROW]))
    with pytest.raises(SplatzooError, match=r"count\.ply: malformed PLY header line .*element <name> <count>"):
        read_ply_vertices(path)


def test_ascii_with_fewer_rows_than_promised(tmp_path):
    path = tmp_path / "short.ply"
    row = " ".join(["0.000000"] * len(PROPS))
    path.write_bytes(ascii_ply(3, [row]))   # bytes enough for 3 short rows, but only one row
    with pytest.raises(SplatzooError, match=r"short\.ply is truncated: .*promises 3 vertices .* only 1 row"):
        read_ply_vertices(path)
    path.write_bytes(ascii_ply(2, [row, ROW.replace("1", "x")]))
    with pytest.raises(SplatzooError, match=r"vertex row 2 .* does not hold 13 numbers"):
        read_ply_vertices(path)
    path.write_bytes(ascii_ply(2, [row, "0 0 0"]))
    with pytest.raises(SplatzooError, match=r"vertex row 2 .* does not hold 13 numbers"):
        read_ply_vertices(path)
    path.write_bytes(ascii_ply(2, [row, row], comments=["splatzoo model 2dgs"]))
    assert splatzoo.load_ply(path).num_primitives == 2  # the same file, complete, loads


@pytest.mark.parametrize("old,new,message", [
    (b"format ascii 1.0", b"format", r"malformed PLY header line 2 'format'"),
    (b"format ascii 1.0\n", b"", r"no 'format' line"),
    (b"property float y", b"property float", r"malformed PLY header line .*'property <type> <name>'"),
    (b"property float y", b"property list uchar y", r"'property list <count type> <item type> <name>'"),
    (b"property float y", b"property float x", r"property x is declared twice"),
    (b"comment splatzoo model 2dgs", b"comment \xff\xfe\x00\x01", r"header holds binary data"),
])
def test_malformed_headers(tmp_path, old, new, message):
    data = ascii_ply(1, [ROW], comments=["splatzoo model 2dgs"])
    assert old in data
    path = tmp_path / "bad.ply"
    path.write_bytes(data.replace(old, new))
    with pytest.raises(SplatzooError, match=message):
        splatzoo.load_ply(path)


def _with_comment(tmp_path, model, old: str, new: str) -> Path:
    """A real export of `model` with one header comment replaced."""
    path = save_ply(model, tmp_path / "m.ply")
    header, body = path.read_bytes().split(b"end_header\n", 1)
    assert old.encode() in header
    path.write_bytes(header.replace(old.encode(), new.encode()) + b"end_header\n" + body)
    return path


def test_crafted_config_comment_allocates_nothing(tmp_path, wide_model):
    model = small_model(wide_model, width=2)
    path = _with_comment(tmp_path, model, '"width":2', '"width":1000000000')
    start = time.perf_counter()
    with pytest.raises(SplatzooError, match=r"'extra' .* needs 1000000000 properties but the file has \d+"):
        splatzoo.load_ply(path)
    assert time.perf_counter() - start < 1.0
    path = _with_comment(tmp_path, small_model(), '"n_waves":4', '"n_waves":1000000000')
    with pytest.raises(SplatzooError, match=r"m\.ply.*n_waves must be at most 30"):
        splatzoo.load_ply(path)


def test_config_comment_must_be_an_object_and_model_known(tmp_path):
    model = small_model()
    config = json.dumps(model.checkpoint()["config"], separators=(",", ":"))
    path = _with_comment(tmp_path, model, config, "[4]")
    with pytest.raises(SplatzooError, match=r"'splatzoo config' header comment must be a JSON object"):
        splatzoo.load_ply(path)
    path = _with_comment(tmp_path, model, "splatzoo model gabor", "splatzoo model gabr")
    with pytest.raises(UnknownNameError, match=r"m\.ply.*unknown model 'gabr'"):
        splatzoo.load_ply(path)


def test_a_key_named_twice_is_refused_in_every_json_splatzoo_reads_back(tmp_path):
    """json.loads keeps the last of two equal keys; a file splatzoo wrote never names one twice, so an edited one
    that does is refused rather than read one way here and another way by a tool that keeps the first."""
    import struct
    import zlib

    from splatzoo.io import read_json
    from splatzoo.packing import header_dictionary, pack_checkpoint

    (tmp_path / "r.json").write_text('{"model": "2dgs", "train": {"seed": 0, "seed": 1}}')
    with pytest.raises(SplatzooError, match=r"r\.json is damaged \(the key 'seed' appears more than once"):
        read_json(tmp_path / "r.json", "run record", "train the run again")
    model = small_model()
    config = json.dumps(model.checkpoint()["config"], separators=(",", ":"))
    path = _with_comment(tmp_path, model, config, config[:-1] + ',"sh_degree":0}')
    with pytest.raises(SplatzooError, match=r"'splatzoo config' header comment is not valid JSON \(the key "
                                            r"'sh_degree' appears more than once"):
        splatzoo.load_ply(path)
    data = pack_checkpoint(model.checkpoint(), "8bit")
    (length,) = struct.unpack_from("<I", data, 4)
    text = zlib.decompressobj(zdict=header_dictionary()).decompress(data[8:8 + length]).decode()
    assert text.startswith("{")
    text = zlib.compress(('{"precision":"float32",' + text[1:]).encode())   # version 1: no dictionary
    (tmp_path / "m.szp").write_bytes(data[:4] + struct.pack("<I", len(text)) + text + data[8 + length:])
    with pytest.raises(SplatzooError, match=r"header is not valid compressed JSON \(the key 'precision' appears"):
        load_model(tmp_path / "m.szp")


def test_non_finite_values_in_a_ply(tmp_path):
    model = small_model("2dgs")
    with torch.no_grad():
        model.log_scales[2, 1] = float("nan")
    path = save_ply(model, tmp_path / "nan.ply")
    with pytest.raises(SplatzooError, match=r"nan\.ply: parameter 'log_scales' has 1 non-finite"):
        splatzoo.load_ply(path)


# --- export -----------------------------------------------------------------------------------------------------

def test_export_never_overwrites_the_model(tmp_path):
    run = tmp_path / "run"
    save_model(small_model(), run / "model.pt")
    before = (run / "model.pt").read_bytes()
    with pytest.raises(SplatzooError, match=r"export writes a PLY.*--out must end in \.ply.*run/model\.ply"):
        export_run(run, run / "model.pt")
    with pytest.raises(SplatzooError, match=r"must end in \.ply"):
        export_run(run / "model.pt", tmp_path / "out.txt")
    res = CliRunner().invoke(app, ["export", str(run), "--out", str(run / "model.pt")])
    assert res.exit_code != 0 and isinstance(res.exception, SplatzooError)
    assert (run / "model.pt").read_bytes() == before
    assert load_model(run / "model.pt").num_primitives == 12
    odd = tmp_path / "weights.ply"   # a model file that happens to be named .ply
    odd.write_bytes(before)
    with pytest.raises(SplatzooError, match="refusing to export onto the model being read"):
        export_run(odd, odd)
    assert odd.read_bytes() == before
    assert export_run(run / "model.pt", tmp_path / "model.PLY").is_file()


def test_model_files_in_other_float_types_or_out_of_range_surfels(tmp_path):
    """A half or bfloat16 entry is read as float32 (and the model saves packed); a double beyond float32's range and
    a quaternion the rasterizer refuses are named at load, not at the first render."""
    import torch

    from splatzoo.errors import SplatzooError
    from splatzoo.zoo import create_model, load_model, save_model

    model = create_model("2dgs", torch.randn(5, 3), torch.rand(5, 3), sh_degree=1)
    save_model(model, tmp_path / "m.pt")
    ckpt = torch.load(tmp_path / "m.pt", weights_only=True)
    for dtype in (torch.bfloat16, torch.float16, torch.float64):
        edited = {**ckpt, "state": {**ckpt["state"], "sh_dc": ckpt["state"]["sh_dc"].to(dtype)}}
        torch.save(edited, tmp_path / "e.pt")
        loaded = load_model(tmp_path / "e.pt")
        assert all(t.dtype == torch.float32 for t in loaded.state_dict().values() if t.is_floating_point())
        save_model(loaded, tmp_path / "e.szp")
    huge = {**ckpt, "state": {**ckpt["state"], "means": ckpt["state"]["means"].double() * 1e300}}
    torch.save(huge, tmp_path / "huge.pt")
    with pytest.raises(SplatzooError, match="non-finite"):
        load_model(tmp_path / "huge.pt")
    quats = ckpt["state"]["quats"].clone()
    quats[0, 1] = 3e38
    torch.save({**ckpt, "state": {**ckpt["state"], "quats": quats}}, tmp_path / "q.pt")
    with pytest.raises(SplatzooError, match="quats"):
        load_model(tmp_path / "q.pt")
