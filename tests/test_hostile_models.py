"""Hostile model files: a model that draws nothing is refused by name wherever it enters (model.pt, PLY, the splat
formats splat-transform reads), damaged splat files are refused with splat-transform's own message and the user's file
name, geometry the rasterizer would change silently (zero quaternions, huge log-scales) is said, and a model is
checked against the dataset it is to be used with. Every case is a SplatzooError or a warning: no traceback, no hang.
"""
import gzip
import io
import json
import struct
import warnings
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import plyfile
import pytest
import torch
from typer.testing import CliRunner

import splatzoo
from splatzoo.cli import app
from splatzoo.errors import SplatzooError
from splatzoo.export import compensate_viewer_dilation, load_ply, load_source, save_ply
from splatzoo.model_checks import (COLLAPSED_LOG_SCALE, check_draws, check_fits_scene, check_in_view,
                                   check_surfel_count, drawing_problem, repair_geometry, surfel_limit)
from splatzoo.types import Camera
from splatzoo.zoo import load_model, save_model

runner = CliRunner()


def _model(n=40, seed=0, spread=0.5):
    g = torch.Generator().manual_seed(seed)
    model = splatzoo.create_model("2dgs", torch.randn(n, 3, generator=g) * spread, torch.rand(n, 3, generator=g))
    with torch.no_grad():
        model.logit_opacity.fill_(2.0)
    return model


def _edited(model, **values):
    with torch.no_grad():
        for name, value in values.items():
            getattr(model, name).copy_(torch.as_tensor(value).expand_as(getattr(model, name)))
    return model


def _third_party(path: Path, n=30, seed=0, text=False, scales=3, **override) -> Path:
    """A 3DGS PLY as other tools write it (three scales, no splatzoo header; a 2DGS one with two), with columns
    overridden."""
    rng = np.random.default_rng(seed)
    cols = {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n)}
    cols.update({f"f_dc_{i}": rng.normal(size=n) for i in range(3)})
    cols["opacity"] = rng.normal(size=n) + 2
    cols.update({f"scale_{i}": rng.uniform(-4, -2, n) for i in range(scales)})
    cols.update({f"rot_{i}": rng.normal(size=n) for i in range(4)})
    for k, v in override.items():
        cols[k] = np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy() if np.ndim(v) == 0 else np.asarray(v)
    arr = np.empty(n, dtype=[(k, "<f4") for k in cols])
    for k, v in cols.items():
        arr[k] = v
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=text, byte_order="<").write(str(path))
    return path


# --- a model that draws nothing ------------------------------------------------------------------------------------

def test_drawing_problem_names_each_reason():
    assert drawing_problem(_model()) is None
    assert "0 surfels" in drawing_problem(splatzoo.create_model("2dgs"))
    assert "opacity below 1/255" in drawing_problem(_edited(_model(), logit_opacity=-20.0))
    nan = _edited(_model(), means=float("nan"))
    assert "every one of its 40 surfels has a non-finite" in drawing_problem(nan)
    collapsed = drawing_problem(_edited(_model(), log_scales=-88.0))
    assert "collapsed to a point" in collapsed and "-88" in collapsed
    partly = _model()
    with torch.no_grad():
        partly.log_scales[:5] = -88.0
    assert drawing_problem(partly) is None  # the others draw
    with pytest.raises(SplatzooError, match=r"^here: it holds 0 surfels.*; do this$"):
        check_draws(splatzoo.create_model("2dgs"), "here", "do this")


@pytest.mark.parametrize("case", ["empty", "transparent", "collapsed"])
def test_a_model_file_that_draws_nothing_is_refused(tmp_path, case):
    model = {"empty": lambda: splatzoo.create_model("2dgs"),
             "transparent": lambda: _edited(_model(), logit_opacity=-20.0),
             "collapsed": lambda: _edited(_model(), log_scales=-88.0)}[case]()
    reason = {"empty": "holds 0 surfels", "transparent": "opacity below 1/255", "collapsed": "collapsed"}[case]
    save_model(model, tmp_path / "model.pt")
    with pytest.raises(SplatzooError, match=rf"model file {tmp_path / 'model.pt'}: .*{reason}"):
        load_model(tmp_path / "model.pt")
    save_model(model, tmp_path / "model.szp")
    with pytest.raises(SplatzooError, match=reason):
        load_model(tmp_path / "model.szp")
    for text in (False, True):
        ply = save_ply(model, tmp_path / f"model-{text}.ply", text=text)
        with pytest.raises(SplatzooError, match=rf"{ply}: .*{reason}.*export the model again"):
            load_ply(ply)
        with pytest.raises(SplatzooError, match=reason):
            load_source(ply)


@pytest.mark.parametrize("text", [False, True])
def test_third_party_plys_that_draw_nothing_are_refused(tmp_path, text):
    with pytest.raises(SplatzooError, match="holds 0 surfels"):
        load_ply(_third_party(tmp_path / "empty.ply", n=0, text=text))
    with pytest.raises(SplatzooError, match="every one of its 30 surfels has an opacity below 1/255"):
        load_ply(_third_party(tmp_path / "clear.ply", text=text, opacity=-30.0))
    with pytest.raises(SplatzooError, match="every one of its 30 surfels has collapsed to a point"):
        load_ply(_third_party(tmp_path / "points.ply", text=text, scale_0=-88.0, scale_1=-88.0, scale_2=-88.0))


def test_commands_refuse_a_model_that_draws_nothing(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.model_files import open_model
    from splatzoo.viewer import viewer_source

    data = make_synthetic_scene("plain", tmp_path / "data", views=3, width=16, height=16)
    empty = _third_party(tmp_path / "empty.ply", n=0)
    for args in (["eval", str(empty), "--data", str(data), "--backend", "reference"],
                 ["render", str(empty), "--data", str(data), "--backend", "reference"],
                 ["train", str(data), "--init-from", str(empty), "--iterations", "2", "--backend", "reference",
                  "--out", str(tmp_path / "run")]):
        res = runner.invoke(app, args)
        assert isinstance(res.exception, SplatzooError) and "holds 0 surfels" in str(res.exception), (args, res.output)
    assert not (tmp_path / "run" / "model.pt").exists()
    with pytest.raises(SplatzooError, match="holds 0 surfels"):
        viewer_source(open_model(empty, latest=True))
    # the scene checks take a loaded dataset as it is
    from splatzoo.data import load_scene

    scene = load_scene(data)
    check_fits_scene(_model(n=40, spread=0.2), scene, "m.ply")
    far = _model()
    with torch.no_grad():
        far.means.add_(torch.tensor([1e11, 0.0, 0.0]))
    with pytest.raises(SplatzooError, match="none of its 40 surfels lies in front"):
        check_fits_scene(far, scene, "m.ply")
    with pytest.raises(SplatzooError, match=f"more than the {surfel_limit(scene):,} pixels"):
        check_fits_scene(_model(n=surfel_limit(scene) + 1, spread=0.2), scene, "m.ply")


# --- geometry the rasterizer would change without a word ------------------------------------------------------

def test_zero_quaternions_become_the_identity_with_a_warning(tmp_path):
    rot = np.random.default_rng(1).normal(size=(30, 4))
    rot[:4] = 0.0
    for layout in ("3dgs", "2dgs"):
        cols = {f"rot_{i}": rot[:, i] for i in range(4)}
        path = _third_party(tmp_path / f"{layout}.ply", scales=3 if layout == "3dgs" else 2, **cols)
        with pytest.warns(UserWarning, match=r"4 of its 30 surfels have a zero rotation quaternion.*identity"):
            model = load_ply(path)
        q = model.quats.detach()
        assert torch.all(q.norm(dim=1) > 0.5)
        if layout == "2dgs":
            assert torch.equal(q[:4], torch.tensor([[1.0, 0, 0, 0]]).expand(4, 4))
    model = _model()
    with torch.no_grad():
        model.quats[:3] = 0.0
    save_model(model, tmp_path / "model.pt")
    with pytest.warns(UserWarning, match=r"model file .*: 3 of its 40 surfels have a zero rotation quaternion"):
        back = load_model(tmp_path / "model.pt")
    assert torch.equal(back.quats.detach()[:3], torch.tensor([[1.0, 0, 0, 0]]).expand(3, 4))


@pytest.mark.parametrize("huge", [100.0, 88.0])
def test_huge_log_scales_are_said_with_their_count(tmp_path, huge):
    scales = np.full(30, -3.0)
    scales[:2] = huge
    path = _third_party(tmp_path / "big.ply", scale_0=scales, scale_1=scales, scale_2=np.full(30, -9.0))
    with pytest.warns(UserWarning, match=r"2 of its 30 surfels have log-scales above 18\.4\d* \(largest "
                                         rf"{huge:g}\): they are drawn at the largest size"):
        model = load_ply(path)
    assert model.num_primitives == 30
    partly = _model()
    with torch.no_grad():
        partly.log_scales[:5] = -88.0
    notes = repair_geometry(partly)
    assert len(notes) == 1 and notes[0].startswith("5 of its 40 surfels have collapsed to a point")
    assert COLLAPSED_LOG_SCALE > -88


# --- a model against the dataset it is used with --------------------------------------------------------------

def _scene(views=4, size=16):
    cams = [Camera.look_at([3 * np.cos(a), 0.0, 3 * np.sin(a)], [0.0, 0.0, 0.0], width=size, height=size,
                           dtype=torch.float32) for a in np.linspace(0, 1, views)]
    from splatzoo.data.scene import camera_extent

    return SimpleNamespace(train=[SimpleNamespace(camera=c) for c in cams], test=[], extent=camera_extent(cams))


def test_check_fits_scene_refuses_a_model_no_training_camera_sees():
    scene = _scene()
    check_fits_scene(_model(), scene, "model.ply")  # around the origin, where the cameras look
    far = _model()
    with torch.no_grad():
        far.means.add_(torch.tensor([0.0, 0.0, 1e11]))
    with pytest.raises(SplatzooError, match=r"^--init-from far.ply: none of its 40 surfels lies in front of any of the "
                                            r"4 training camera\(s\), between depth 0.2 and .*median position"):
        check_fits_scene(far, scene, "--init-from far.ply")
    behind = _model(spread=0.01)
    with torch.no_grad():  # behind every camera: beyond their eyes, seen from the origin
        behind.means.add_(torch.tensor([30.0, 0.0, 30.0]))
    with pytest.raises(SplatzooError, match="none of its 40 surfels lies in front"):
        check_in_view(behind, [v.camera for v in scene.train], "model.pt")


def test_check_fits_scene_refuses_more_surfels_than_training_pixels():
    scene = _scene(views=2, size=4)  # 32 training pixels
    assert surfel_limit(scene) == 32
    check_surfel_count(_model(n=32), scene, "m.ply")
    with pytest.raises(SplatzooError, match=r"^--init-from m.ply: its 40 surfels are more than the 32 pixels of the "
                                            r"dataset's 2 training view\(s\) \(4x4\).*one surfel per 128 pixels"):
        check_fits_scene(_model(n=40), scene, "--init-from m.ply")


def test_commands_check_a_model_file_against_the_dataset(tmp_path):
    """eval/render FILE --data and train --init-from refuse, before anything runs, a model none of whose surfels the
    dataset's cameras see and one with more surfels than the dataset has pixels; no run folder is left."""
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("plain", tmp_path / "data", views=3, width=8, height=8)  # 192 training pixels
    far = _model()
    with torch.no_grad():
        far.means.add_(torch.tensor([1e11, 0.0, 0.0]))
    save_ply(far, tmp_path / "far.ply")
    save_ply(_model(n=400, spread=0.2), tmp_path / "many.ply")
    for name, says in (("far.ply", "none of its 40 surfels lies in front"), ("many.ply", "its 400 surfels are more")):
        path = tmp_path / name
        for args in (["eval", str(path), "--data", str(data), "--backend", "reference"],
                     ["render", str(path), "--data", str(data), "--backend", "reference", "--out",
                      str(tmp_path / "renders")],
                     ["train", str(data), "--init-from", str(path), "--iterations", "2", "--backend", "reference",
                      "--out", str(tmp_path / "run")]):
            res = runner.invoke(app, args)
            assert isinstance(res.exception, SplatzooError) and says in str(res.exception), (args, res.output)
        assert not (tmp_path / "run").exists() and not (tmp_path / "renders").exists()


def test_ply_for_3dgs_viewers_refuses_a_model_no_camera_sees():
    cam = Camera.look_at([0, 0, -3], [0, 0, 0], width=32, height=32)
    model = _model()
    with torch.no_grad():
        model.means.add_(torch.tensor([0.0, 0.0, -10.0]))  # behind the camera
    before = model.log_scales.detach().clone()
    with pytest.raises(SplatzooError, match=r"ply:viewer=3dgs of the 2dgs model: none of its 40 surfels lies in "
                                            r"front.*ply:viewer=exact"):
        compensate_viewer_dilation(model, [cam], "3dgs")
    assert torch.equal(model.log_scales.detach(), before)  # nothing half-done
    far = _model()
    with torch.no_grad():
        far.means.add_(torch.tensor([0.0, 0.0, 1e11]))
    with pytest.raises(SplatzooError, match="none of its 40 surfels lies in front"):
        compensate_viewer_dilation(far, [cam], "mip")


# --- splat-transform's messages ------------------------------------------------------------------------------------

NODE_STDERR = """  ✗ Error: invalid .spz file header
    at parseSpz (file:///x/cli.mjs:37213:15)
    at async readSpz (file:///x/cli.mjs:37331:21)
    at async readFile (file:///x/cli.mjs:38999:21)
    at async openInput (file:///x/cli.mjs:52178:30)
    at async main (file:///x/cli.mjs:52218:27)
    at async file:///x/bin/cli.mjs:5:1
✗ failed in 0.010s  [peak cpu=85.0MB]
"""
NODE_UNCAUGHT = """file:///x/cli.mjs:12
    const a = b ??= c;
                ^^^

SyntaxError: Unexpected token '??='
    at ModuleLoader.moduleStrategy (node:internal/modules/esm/translators:117:18)

Node.js v14.0.0
"""


def test_tool_message_keeps_the_error_line_and_drops_the_stack():
    from splatzoo.splat_tools import tool_message

    assert tool_message(NODE_STDERR) == "Error: invalid .spz file header"
    assert tool_message(NODE_UNCAUGHT) == "SyntaxError: Unexpected token '??='"
    assert tool_message("", "something odd\n    at x (y:1:2)\n") == "something odd"


def _splat_transform():
    from splatzoo.splat_tools import find_splat_transform

    try:
        return find_splat_transform()
    except SplatzooError as e:
        pytest.skip(f"splat-transform is not installed here ({str(e)[:80]})")


def _splat(n=20, *, seed=0, alpha=255, rotation=(255, 128, 128, 128), positions=None, scale=0.05) -> bytes:
    """An antimatter15 .splat: 32-byte records of position, linear scale, RGBA and rotation bytes (q * 128 + 128)."""
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("q", "u1", 4)])
    rec["p"] = rng.normal(size=(n, 3)) if positions is None else positions
    rec["s"] = scale
    rec["c"] = [200, 100, 50, alpha]
    rec["q"] = rotation
    return rec.tobytes()


def _ksplat(n=20, *, seed=0, alpha=255, quats=None) -> bytes:
    """A GaussianSplats3D .ksplat of one uncompressed section (mode 0): a 4096-byte header, a 1024-byte section
    header, then per splat float32 position, linear scale, rotation (w, x, y, z) and RGBA bytes."""
    rng = np.random.default_rng(seed)
    head = bytearray(4096)
    head[1] = 1  # version 0.1
    struct.pack_into("<I", head, 4, 1)  # sections
    struct.pack_into("<I", head, 16, n)  # splats
    section = bytearray(1024)
    struct.pack_into("<II", section, 0, n, n)
    rec = np.zeros(n, dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("q", "<f4", 4), ("c", "u1", 4)])
    rec["p"] = rng.normal(size=(n, 3))
    rec["s"] = 0.05
    rec["q"] = [1, 0, 0, 0] if quats is None else quats
    rec["c"] = [200, 100, 50, alpha]
    return bytes(head) + bytes(section) + rec.tobytes()


@pytest.fixture(scope="module")
def packed(tmp_path_factory):
    """Good SPZ (v3 and v4), SOG and compressed PLY files of one 2dgs model, and the PLY they came from."""
    _splat_transform()
    from splatzoo.splat_tools import convert_file

    folder = tmp_path_factory.mktemp("packed")
    ply = save_ply(_model(n=50), folder / "m.ply")
    out = {"ply": ply}
    for name, args in (("m.spz", ["--spz-version", "3"]), ("m4.spz", ["--spz-version", "4"]), ("m.sog", []),
                       ("m.compressed.ply", [])):
        out[name] = convert_file(ply, folder / name, args=args)
    return out


def _no_trace(message: str):
    assert "    at " not in message and "splatzoo-load-" not in message and "cli.mjs" not in message, message


def _damaged(packed, name: str) -> bytes:
    data = packed[name].read_bytes()
    return data[: len(data) // 2]


def _spz_with(packed, **fields) -> bytes:
    raw = bytearray(gzip.decompress(packed["m.spz"].read_bytes()))
    offsets = {"version": (4, "<I"), "count": (8, "<I"), "fractional_bits": (13, "<B")}
    for k, v in fields.items():
        struct.pack_into(offsets[k][1], raw, offsets[k][0], v)
    return gzip.compress(bytes(raw))


def _sog_with(packed, meta=None, drop=()) -> bytes:
    z = zipfile.ZipFile(packed["m.sog"])
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as w:
        for name in z.namelist():
            if name in drop:
                continue
            data = z.read(name)
            if name == "meta.json" and meta is not None:
                data = meta(json.loads(data)) if callable(meta) else meta
                data = data if isinstance(data, bytes) else json.dumps(data).encode()
            w.writestr(name, data)
    return out.getvalue()


DAMAGED = {  # file name: (bytes of the damaged file, what the message must say)
    "garbage.spz": (lambda p: b"\x00not an spz at all" * 4, "invalid .spz file header"),
    "cut.spz": (lambda p: _damaged(p, "m.spz"), "unexpected end of file"),
    "short.spz": (lambda p: gzip.compress(gzip.decompress(p["m.spz"].read_bytes())[:200]), "File too small"),
    "empty.spz": (lambda p: b"", "File too small"),
    "version.spz": (lambda p: _spz_with(p, version=9), "Unsupported .spz version 9"),
    "toomany.spz": (lambda p: _spz_with(p, count=10 ** 9), "File too small for .spz payload"),
    "cut4.spz": (lambda p: _damaged(p, "m4.spz"), "header declares 50, so the file is damaged"),
    "none.spz": (lambda p: _spz_with(p, count=0), "found no splats in it"),
    "bits.spz": (lambda p: _spz_with(p, fractional_bits=255), "255 fractional bits"),
    "garbage.sog": (lambda p: b"PK\x03\x04" + b"\x00" * 60, "invalid zip file"),
    "cut.sog": (lambda p: _damaged(p, "m.sog"), "invalid zip file"),
    "nometa.sog": (lambda p: _sog_with(p, drop=("meta.json",)), "meta.json"),
    "json.sog": (lambda p: _sog_with(p, meta=b"{not json"), "SyntaxError"),
    "none.sog": (lambda p: _sog_with(p, meta=lambda m: {**m, "count": 0}), "found no splats in it"),
    "toomany.sog": (lambda p: _sog_with(p, meta=lambda m: {**m, "count": 10 ** 9}), "too small for count"),
    "cut.compressed.ply": (lambda p: _damaged(p, "m.compressed.ply"), "short vertex read"),
    "odd.splat": (lambda p: _splat()[:-5], "not a multiple of 32 bytes"),
    "empty.splat": (lambda p: b"", "file is empty"),
    "garbage.ksplat": (lambda p: b"\x07" * 5000, "Unsupported version 7.7"),
    "short.ksplat": (lambda p: _ksplat()[:100], "File too small"),
    "none.ksplat": (lambda p: _ksplat()[:16] + b"\x00" * 4 + _ksplat()[20:], "file is empty"),
}


@pytest.mark.parametrize("name", sorted(DAMAGED))
def test_a_damaged_splat_file_is_refused_with_splat_transforms_reason(tmp_path, packed, name):
    from splatzoo.splat_tools import splat_format

    make, said = DAMAGED[name]
    path = tmp_path / name
    path.write_bytes(make(packed))
    with pytest.raises(SplatzooError) as caught:
        load_source(path)
    message = str(caught.value)
    assert str(path) in message and splat_format(path) in message and said in message, message
    _no_trace(message)
    res = runner.invoke(app, ["export", str(path), "--out", str(tmp_path / "x.ply")])
    assert isinstance(res.exception, SplatzooError) and said in str(res.exception)
    assert not (tmp_path / "x.ply").exists()


def test_good_splat_files_load(tmp_path, packed):
    for name in ("m.spz", "m4.spz", "m.sog", "m.compressed.ply"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # SPZ holds no 2DGS tag: read as 3DGS Gaussians, with a note
            assert load_source(packed[name])[0].num_primitives == 50
    (tmp_path / "m.splat").write_bytes(_splat())
    (tmp_path / "m.ksplat").write_bytes(_ksplat())
    for name in ("m.splat", "m.ksplat"):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            model, _ = load_source(tmp_path / name)
        assert model.num_primitives == 20
        assert all(str(tmp_path / name) in str(w.message) and "splatzoo-load-" not in str(w.message) for w in seen)


def test_splat_files_that_draw_nothing_are_refused_by_name(tmp_path, packed):
    from splatzoo.splat_tools import convert_file

    clear = _third_party(tmp_path / "clear.ply", opacity=-30.0)
    flat = _third_party(tmp_path / "flat.ply", scale_0=-88.0, scale_1=-88.0, scale_2=-88.0)
    files = {"clear.spz": convert_file(clear, tmp_path / "clear.spz", args=["--spz-version", "3"]),
             "clear.sog": convert_file(clear, tmp_path / "clear.sog"),
             "flat.sog": convert_file(flat, tmp_path / "flat.sog"),
             "clear.compressed.ply": convert_file(clear, tmp_path / "clear.compressed.ply")}
    for name, data in (("clear.splat", _splat(alpha=0)), ("clear.ksplat", _ksplat(alpha=0)),
                       ("dot.splat", _splat(positions=np.zeros((20, 3))))):
        files[name] = tmp_path / name
        files[name].write_bytes(data)
    for name, path in files.items():
        reason = ("lies at the one point" if name.startswith("dot") else "collapsed to a point"
                  if name.startswith("flat") else "opacity below 1/255")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(SplatzooError, match=reason) as caught:
                load_source(path)
        assert str(path) in str(caught.value), str(caught.value)
        _no_trace(str(caught.value))
    (tmp_path / "nan.splat").write_bytes(_splat(positions=np.full((20, 3), np.nan)))
    with pytest.raises(SplatzooError, match=r"nan.splat \(read through splat-transform\): parameter 'means' has 60 "
                                            r"non-finite") as caught:
        load_source(tmp_path / "nan.splat")
    _no_trace(str(caught.value))


def test_splat_files_without_rotations_say_how_many(tmp_path, packed):
    rotation = np.tile([255, 128, 128, 128], (20, 1))
    rotation[:3] = 128  # a zero quaternion: splat-transform would make each an arbitrary rotation
    (tmp_path / "r.splat").write_bytes(_splat(rotation=rotation))
    with pytest.warns(UserWarning, match=r"r.splat \(read through splat-transform\): 3 of its 20 surfels have a zero "
                                         "rotation quaternion"):
        model, _ = load_source(tmp_path / "r.splat")
    assert model.num_primitives == 20
    quats = np.zeros((20, 4))
    quats[:, 0] = 1
    quats[5:7] = 0
    (tmp_path / "r.ksplat").write_bytes(_ksplat(quats=quats))
    with pytest.warns(UserWarning, match=r"r.ksplat \(read through splat-transform\): 2 of its 20 surfels have a "
                                         "zero rotation quaternion"):
        load_source(tmp_path / "r.ksplat")


def test_an_opacity_of_exactly_zero_or_one_in_another_tools_ply_is_not_damage(tmp_path):
    """A logit of -inf / +inf is an opacity of 0 / 1 (what splat-transform reads from a compressed PLY's 8 bits)."""
    from splatzoo.export import SATURATED_LOGIT

    opacity = np.full(30, 1.0)
    opacity[:3], opacity[3:5] = -np.inf, np.inf
    model = load_ply(_third_party(tmp_path / "o.ply", opacity=opacity))
    logits = model.logit_opacity.detach()
    assert torch.isfinite(logits).all() and torch.all(logits[:3] == -SATURATED_LOGIT)
    assert torch.all(logits[3:5] == SATURATED_LOGIT) and torch.all(logits[5:] == 1.0)
    with pytest.raises(SplatzooError, match="every one of its 30 surfels has an opacity below 1/255"):
        load_ply(_third_party(tmp_path / "none.ply", opacity=-np.inf))
