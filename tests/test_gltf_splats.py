"""splatzoo models as glTF binaries with KHR_gaussian_splatting (splatzoo.gltf_splats): the round trip renders
identically, rich members are baked, another tool's 3DGS glb is flattened as a 3DGS PLY is, node transforms are
applied, damaged and hostile files end in a named error; the Khronos glTF validator finds nothing wrong beyond the
extension's attribute names it does not know yet; and the PlayCanvas engine, a real reader of the extension, draws the
export from a splatzoo camera as splatzoo does."""
import json
import math
import os
import shutil
import struct
import subprocess
import warnings
from pathlib import Path

import browser_viewers as bv
import numpy as np
import pytest
import torch

from splatzoo import Camera, SplatzooError, create_model
from splatzoo.geometry import normals_to_quats, rgb_to_sh0
from splatzoo.gltf_export import GlbSplatOptions, export_glb_splats, write_glb_splats
from splatzoo.gltf_splats import EXTENSION, SURFEL_EXTENSION, glb_splat_bytes, is_glb, read_glb_splats

ROOT = Path(__file__).resolve().parents[1]
VALIDATOR = ROOT / "tools" / "gltf-validator"
CAMERA = Camera.look_at([0.3, -0.4, -3.0], [0.0, 0.0, 0.0], width=48, height=40, fov_deg=55)


def random_2dgs(n=60, degree=3, seed=0):
    """A 2dgs model with unnormalised quaternions, SH of `degree` and the anti-aliasing flag."""
    g = torch.Generator().manual_seed(seed)
    model = create_model("2dgs", points=torch.randn(n, 3, generator=g) * 0.4, colors=torch.rand(n, 3, generator=g),
                         sh_degree=degree)
    with torch.no_grad():
        model.quats.copy_(torch.randn(n, 4, generator=g) * 2.5)
        model.log_scales.copy_(torch.randn(n, 2, generator=g) * 0.3 - 2.5)
        model.logit_opacity.copy_(torch.randn(n, generator=g) * 2)
        model.sh_rest.copy_(torch.randn(model.sh_rest.shape, generator=g) * 0.15)
    model.antialias = True
    return model


def render(model, camera=CAMERA, background=(1.0, 1.0, 1.0)):
    with torch.no_grad():
        return model.render(camera, background=torch.tensor(background), backend="cpu").rgb.double().numpy()


def glb_parts(data: bytes) -> tuple[dict, bytes]:
    """(JSON, binary chunk) of a GLB."""
    (n,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20:20 + n])
    (m,) = struct.unpack_from("<I", data, 20 + n)
    return doc, data[28 + n:28 + n + m]


def pack(doc: dict, blob: bytes) -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob = blob + b"\0" * (-len(blob) % 4)
    return b"".join([b"glTF", struct.pack("<II", 2, 28 + len(text) + len(blob)), struct.pack("<I", len(text)),
                     b"JSON", text, struct.pack("<I", len(blob)), b"BIN\0", blob])


def attribute(doc, blob, semantic):
    """The float32 values of an attribute of the first primitive [count, width]."""
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][semantic]]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    return np.frombuffer(blob, "<f4", acc["count"] * width, view["byteOffset"]).reshape(acc["count"], width)


def splat_glb(means, quats_xyzw, scales, opacity, sh, *, extension=None) -> bytes:
    """A GLB as another tool writes it: float32 KHR_gaussian_splatting attributes (sh [N, bands, 3]), no flag."""
    blob, views, accessors, attributes = bytearray(), [], [], {}
    n = len(means)

    def add(semantic, values, type_):
        data = np.ascontiguousarray(values, "<f4")
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes})
        blob.extend(data.tobytes())
        acc = {"bufferView": len(views) - 1, "componentType": 5126, "count": n, "type": type_}
        if semantic == "POSITION":
            acc["min"], acc["max"] = data.min(0).tolist(), data.max(0).tolist()
        accessors.append(acc)
        attributes[semantic] = len(accessors) - 1

    add("POSITION", means, "VEC3")
    add(f"{EXTENSION}:ROTATION", quats_xyzw, "VEC4")
    add(f"{EXTENSION}:SCALE", scales, "VEC3")
    add(f"{EXTENSION}:OPACITY", opacity, "SCALAR")
    band = 0
    for level in range(round(math.sqrt(sh.shape[1]))):
        for coef in range(2 * level + 1):
            add(f"{EXTENSION}:SH_DEGREE_{level}_COEF_{coef}", sh[:, band], "VEC3")
            band += 1
    doc = {"asset": {"version": "2.0", "generator": "another tool"}, "extensionsUsed": [EXTENSION],
           "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": attributes, "mode": 0, "extensions": {EXTENSION: extension or {
               "kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}]}],
           "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    return pack(doc, bytes(blob))


# --- writing and reading ---------------------------------------------------------------------------------------

def test_round_trip_renders_equal(tmp_path):
    model = random_2dgs()
    with torch.no_grad():
        model.quats[3] = 0.0  # no rotation: drawn (and written) as the identity
    path = write_glb_splats(model, tmp_path / "model.glb")
    assert is_glb(path) and not list(tmp_path.glob(".*"))  # atomic: no temporary file left
    back = read_glb_splats(path)
    assert back.name == "2dgs" and back.config.sh_degree == 3 and back.antialias
    assert np.abs(render(back) - render(model)).max() < 1e-5
    q = torch.nn.functional.normalize(model.quats.detach(), dim=1)
    q[3] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    assert torch.allclose(back.quats, q, atol=1e-6)
    for name in ("means", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(back, name), getattr(model, name).detach()), name
    assert torch.allclose(back.log_scales, model.log_scales.detach(), atol=1e-6)
    assert torch.allclose(back.logit_opacity, model.logit_opacity.detach(), atol=1e-4)

    # the file itself: the spec's layout, glTF's quaternion order, linear values, the flat third axis, the flag
    doc, blob = glb_parts(path.read_bytes())
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0 and doc["extensionsUsed"] == [EXTENSION, SURFEL_EXTENSION]
    ext = prim["extensions"][EXTENSION]
    assert ext["kernel"] == "ellipse" and ext["colorSpace"] == "srgb_rec709_display"
    assert ext["extensions"][SURFEL_EXTENSION] == {"antialias": True, "viewer": "exact"}
    assert np.allclose(attribute(doc, blob, f"{EXTENSION}:ROTATION"), q[:, [1, 2, 3, 0]].numpy(), atol=1e-7)
    scale = attribute(doc, blob, f"{EXTENSION}:SCALE")
    assert np.allclose(scale[:, :2], model.log_scales.detach().exp().numpy(), rtol=1e-6) and (scale[:, 2] == 0).all()
    assert np.allclose(attribute(doc, blob, f"{EXTENSION}:OPACITY")[:, 0],
                       torch.sigmoid(model.logit_opacity.detach()).numpy(), atol=1e-7)
    semantics = set(prim["attributes"])
    assert {f"{EXTENSION}:SH_DEGREE_{lv}_COEF_{c}" for lv in range(4) for c in range(2 * lv + 1)} <= semantics
    color = attribute(doc, blob, "COLOR_0")
    assert (color >= 0).all() and (color <= 1).all()
    assert np.allclose(color[:, 3], attribute(doc, blob, f"{EXTENSION}:OPACITY")[:, 0])
    pos = doc["accessors"][prim["attributes"]["POSITION"]]
    assert pos["min"] == model.means.detach().min(0).values.tolist()
    # without the fallback colour, and a model without SH
    plain = random_2dgs(degree=0)
    path = write_glb_splats(plain, tmp_path / "plain.glb", color=False)
    doc, _ = glb_parts(path.read_bytes())
    assert "COLOR_0" not in doc["meshes"][0]["primitives"][0]["attributes"]
    assert np.abs(render(read_glb_splats(path)) - render(plain)).max() < 1e-5


def test_writer_refusals(tmp_path):
    model = random_2dgs(degree=0)
    with pytest.raises(SplatzooError, match=r"\.glb file"):
        write_glb_splats(model, tmp_path / "model.ply")
    with pytest.raises(SplatzooError, match="it is a folder"):
        write_glb_splats(model, tmp_path)
    with pytest.raises(SplatzooError, match="viewer='mip' is not known"):
        write_glb_splats(model, tmp_path / "m.glb", viewer="mip")
    with pytest.raises(SplatzooError, match="pass cameras"):
        write_glb_splats(model, tmp_path / "m.glb", viewer="3dgs")
    with torch.no_grad():
        model.means[2, 1] = float("nan")
    with pytest.raises(SplatzooError, match="1 of the model's 60 surfels have a non-finite"):
        write_glb_splats(model, tmp_path / "m.glb")
    assert not list(tmp_path.iterdir())
    with pytest.raises(SplatzooError, match="bake it first"):
        glb_splat_bytes(create_model("gabor", points=torch.zeros(4, 3), colors=torch.zeros(4, 3)))
    with pytest.raises(SplatzooError, match="viewer must be one of"):
        GlbSplatOptions(viewer="x")


def test_viewer_rule_sizes_the_surfels_for_3dgs_viewers(tmp_path):
    from splatzoo.export import compensate_viewer_dilation

    model = random_2dgs(degree=1)
    cams = [Camera.look_at([3 * math.sin(a), -0.5, -3 * math.cos(a)], [0, 0, 0], width=64, height=64)
            for a in np.linspace(0, 2 * math.pi, 6, endpoint=False)]
    path = write_glb_splats(model, tmp_path / "viewer.glb", cameras=cams, viewer="3dgs")
    expected = random_2dgs(degree=1)
    compensate_viewer_dilation(expected, cams, "3dgs")
    assert torch.equal(model.log_scales, random_2dgs(degree=1).log_scales)  # the caller's model is untouched
    with pytest.warns(UserWarning, match="sized for the dilation of 3DGS-style viewers"):
        back = read_glb_splats(path)
    assert np.abs(render(back) - render(expected)).max() < 1e-5
    doc, _ = glb_parts(path.read_bytes())
    flag = doc["meshes"][0]["primitives"][0]["extensions"][EXTENSION]["extensions"][SURFEL_EXTENSION]
    assert flag["viewer"] == "3dgs"


def test_rich_models_are_baked(tmp_path):
    from splatzoo.bake import BakeOptions

    gabor = create_model("gabor", points=torch.randn(30, 3) * 0.3, colors=torch.rand(30, 3), n_waves=2)
    cams = [Camera.look_at([3 * math.sin(a), -0.3, -3 * math.cos(a)], [0, 0, 0], width=32, height=32)
            for a in (0.0, 1.5, 3.0)]
    messages = []
    path = write_glb_splats(gabor, tmp_path / "gabor.glb", cameras=cams,
                            bake=BakeOptions(steps=3, views=3, eval_views=1, backend="cpu"), progress=messages.append)
    assert any("bake error" in m for m in messages)
    doc, _ = glb_parts(path.read_bytes())
    flag = doc["meshes"][0]["primitives"][0]["extensions"][EXTENSION]["extensions"][SURFEL_EXTENSION]
    assert flag["bakedFrom"] == "gabor" and isinstance(flag["bakeDb"], float)
    back = read_glb_splats(path)
    assert back.name == "2dgs" and back.num_primitives >= gabor.num_primitives


def test_exporter_from_run_folder_and_model_file(trained_2dgs, tmp_path):
    from splatzoo.zoo import save_model

    model, view, run = trained_2dgs
    out = export_glb_splats(run, tmp_path / "run.glb")
    assert np.abs(render(read_glb_splats(out), view.camera) - render(model, view.camera)).max() < 1e-5
    save_model(model, tmp_path / "model.pt")
    out = export_glb_splats(tmp_path / "model.pt", tmp_path / "file.glb", color=False)
    assert np.abs(render(read_glb_splats(out), view.camera) - render(model, view.camera)).max() < 1e-5
    sized = export_glb_splats(run, tmp_path / "sized.glb", viewer="3dgs")
    assert sized.stat().st_size > 0
    with pytest.raises(SplatzooError, match="export from the run folder"):
        export_glb_splats(tmp_path / "model.pt", tmp_path / "x.glb", viewer="3dgs")
    with pytest.raises(SplatzooError, match="onto the model being read"):
        export_glb_splats(tmp_path / "file.glb", tmp_path / "file.glb")


def test_another_tools_3dgs_glb_is_read_as_a_3dgs_ply_is(tmp_path):
    """Gaussians with three real axes: the same surfels as load_ply makes of the same Gaussians in a 3DGS PLY."""
    import plyfile

    from splatzoo.model_ply import load_ply

    rng = np.random.default_rng(1)
    n = 40
    means = rng.normal(size=(n, 3)).astype(np.float32) * 0.4
    q = rng.normal(size=(n, 4))
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)   # (w, x, y, z)
    log_s = (rng.normal(size=(n, 3)) * 0.5 - 2.5).astype(np.float32)
    opacity = rng.uniform(0.05, 0.95, n).astype(np.float32)
    sh = (rng.normal(size=(n, 4, 3)) * 0.3).astype(np.float32)
    path = tmp_path / "3dgs.glb"
    path.write_bytes(splat_glb(means, q[:, [1, 2, 3, 0]], np.exp(log_s), opacity, sh))

    names = (["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    rows = np.concatenate([means, sh[:, 0], sh[:, 1:].transpose(0, 2, 1).reshape(n, 9),
                           np.log(opacity / (1 - opacity))[:, None], log_s, q], 1).astype(np.float32)
    arr = np.empty(n, dtype=[(k, "<f4") for k in names])
    for i, k in enumerate(names):
        arr[k] = rows[:, i]
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "3dgs.ply"))
    with pytest.warns(UserWarning, match="3DGS file"):
        from_ply = load_ply(tmp_path / "3dgs.ply")
    with pytest.warns(UserWarning, match="holds 3D Gaussians") as notes:
        from_glb = read_glb_splats(path)
    assert len(notes) == 1
    assert from_glb.config.sh_degree == 1 and not from_glb.antialias
    for name in ("means", "sh_dc", "sh_rest", "quats"):
        assert torch.allclose(getattr(from_glb, name), getattr(from_ply, name), atol=1e-6), name
    assert torch.allclose(from_glb.log_scales, from_ply.log_scales, atol=1e-5)
    assert torch.allclose(from_glb.logit_opacity, from_ply.logit_opacity, atol=1e-4)

    # a flat third axis without the flag (another 2DGS tool): exact, and no note about 3D Gaussians
    path.write_bytes(splat_glb(means, q[:, [1, 2, 3, 0]], np.concatenate([np.exp(log_s[:, :2]), np.zeros((n, 1))], 1),
                               opacity, sh[:, :1]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        flat = read_glb_splats(path)
    assert torch.equal(flat.quats, torch.from_numpy(q)) and flat.config.sh_degree == 0


def test_integer_encodings_and_linear_colours(tmp_path):
    """The spec's quantised encodings (normalised short rotations, unsigned byte opacities) decode; linear colours
    become display colours."""
    model = random_2dgs(n=20, degree=0)
    doc, blob = glb_parts(glb_splat_bytes(model, color=False))
    prim = doc["meshes"][0]["primitives"][0]
    rot = attribute(doc, blob, f"{EXTENSION}:ROTATION")
    opa = attribute(doc, blob, f"{EXTENSION}:OPACITY")[:, 0]
    blob = bytearray(blob)
    for semantic, data, component in ((f"{EXTENSION}:ROTATION", np.round(rot * 32767).astype("<i2"), 5122),
                                      (f"{EXTENSION}:OPACITY", np.round(opa * 255).astype("<u1"), 5121)):
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes})
        blob.extend(data.tobytes() + b"\0" * (-data.nbytes % 4))
        acc = doc["accessors"][prim["attributes"][semantic]]
        acc.update(bufferView=len(doc["bufferViews"]) - 1, componentType=component, normalized=True)
    prim["extensions"][EXTENSION]["colorSpace"] = "lin_rec709_display"
    doc["buffers"][0]["byteLength"] = len(blob)
    path = tmp_path / "quantised.glb"
    path.write_bytes(pack(doc, bytes(blob)))
    with pytest.warns(UserWarning, match="linear colours"):
        back = read_glb_splats(path)
    q = torch.nn.functional.normalize(model.quats.detach(), dim=1)
    assert torch.allclose(back.quats, q, atol=1e-4)
    assert torch.allclose(torch.sigmoid(back.logit_opacity), torch.sigmoid(model.logit_opacity.detach()),
                          atol=0.5 / 255 + 1e-6)
    linear = 0.5 + 0.2820947917738781 * model.sh_dc.detach()[:, 0].double()
    display = torch.where(linear <= 0.0031308, linear * 12.92, 1.055 * linear.clamp_min(0) ** (1 / 2.4) - 0.055)
    assert torch.allclose(0.5 + 0.2820947917738781 * back.sh_dc[:, 0].double(), display, atol=1e-5)


def test_node_transforms_are_applied(tmp_path):
    """The file's splats under a parent node (turned, scaled, moved): the read model, seen from the camera carried by
    the same transform, renders as the model does from the original camera (view-dependent SH included)."""
    model = random_2dgs(degree=3)
    model.antialias = False  # the pixel filter is per pixel, but the flag is not what is tested here
    doc, blob = glb_parts(glb_splat_bytes(model))
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    angle = 1.1
    xyz, w = axis * math.sin(angle / 2), math.cos(angle / 2)
    scale, shift = 1.7, np.array([0.4, -2.0, 5.0])
    doc["nodes"] = [{"children": [1], "translation": shift.tolist(), "rotation": [*xyz.tolist(), w],
                     "scale": [scale] * 3}, {"mesh": 0}]
    path = tmp_path / "moved.glb"
    path.write_bytes(pack(doc, blob))
    moved = read_glb_splats(path)
    R = torch.from_numpy(np.array(_rotation(axis, angle)))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3], T[:3, 3] = scale * R, torch.from_numpy(shift)
    # the camera carried along: world_to_camera' = world_to_camera @ T^-1, its rotation normalised (a uniform scale)
    w2c = CAMERA.world_to_camera @ torch.linalg.inv(T)
    w2c[:3, :] *= scale
    camera = Camera(w2c, CAMERA.K, CAMERA.width, CAMERA.height)
    assert render(model).std() > 0.02  # not a blank frame
    assert np.abs(render(moved, camera) - render(model)).max() < 2e-4


def _rotation(axis, angle):
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    return [[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
            [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
            [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]]


# --- damaged and hostile files ---------------------------------------------------------------------------------

def _mutate(edit):
    """A file from a good one: edit(doc, blob) changes the JSON in place and may return new bytes for the blob."""
    def make(good: bytes) -> bytes:
        doc, blob = glb_parts(good)
        new = edit(doc, blob)
        return pack(doc, new if isinstance(new, bytes) else blob)
    return make


def _attr(doc, semantic):
    return doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][semantic]]


def _set_values(semantic, index, values):
    def edit(doc, blob):
        acc = _attr(doc, semantic)
        view = doc["bufferViews"][acc["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        arr = np.frombuffer(blob, "<f4", acc["count"] * width, view["byteOffset"]).reshape(-1, width).copy()
        arr[index] = values
        return blob[:view["byteOffset"]] + arr.tobytes() + blob[view["byteOffset"] + arr.nbytes:]
    return _mutate(edit)


def _drop(semantic):
    return _mutate(lambda doc, blob: doc["meshes"][0]["primitives"][0]["attributes"].pop(semantic))


def _acc(semantic, **fields):
    return _mutate(lambda doc, blob: _attr(doc, semantic).update(fields))


def _ext(**fields):
    return _mutate(lambda doc, blob: doc["meshes"][0]["primitives"][0]["extensions"][EXTENSION].update(fields))


def _json_chunk(text: bytes) -> bytes:
    """A GLB of just this JSON chunk."""
    return b"glTF" + struct.pack("<II", 2, 20 + len(text)) + struct.pack("<I", len(text)) + b"JSON" + text


ROT, SCALE, OPA = (f"{EXTENSION}:{s}" for s in ("ROTATION", "SCALE", "OPACITY"))
HOSTILE = {
    "empty": (lambda good: b"", "not a glTF binary"),
    "a PLY": (lambda good: b"ply\nformat ascii 1.0\nend_header\n", "not a glTF binary"),
    "glTF JSON": (lambda good: b'{"asset": {"version": "2.0"}}', r"glTF JSON file \(\.gltf\)"),
    "version 1": (lambda good: good[:4] + struct.pack("<I", 1) + good[8:], "version 1"),
    "truncated": (lambda good: good[:len(good) // 2], "is truncated"),
    "trailing bytes": (lambda good: good + b"\0" * 8, "bytes beyond"),
    "chunk past the end": (lambda good: good[:12] + struct.pack("<I", 10 ** 9) + good[16:], "is truncated"),
    "broken JSON": (lambda good: good[:20] + b"x" + good[21:], "JSON that cannot be parsed"),
    "deep JSON": (lambda good: _json_chunk(b"[" * 100000 + b"]" * 100000), "nested too deeply"),
    "JSON list": (lambda good: _json_chunk(b"[1, 2]  "), "holds a JSON list"),
    "no asset": (_mutate(lambda doc, blob: doc.pop("asset")), "no asset.version"),
    "required extension": (_mutate(lambda doc, blob: doc.update(extensionsRequired=["KHR_spz_gaussian_splats"])),
                           "requires the glTF extension"),
    "no splats": (_mutate(lambda doc, blob: doc["meshes"][0]["primitives"][0].pop("extensions")),
                  "holds no Gaussian splats"),
    "triangles": (_mutate(lambda doc, blob: doc["meshes"][0]["primitives"][0].update(mode=4)), "needs POINTS"),
    "no kernel": (_ext(kernel=None), "no kernel"),
    "colour space": (_ext(colorSpace="acescg"), "colorSpace 'acescg'"),
    "no rotation": (_drop(ROT), "lacks the attribute"),
    "no SH": (_drop(f"{EXTENSION}:SH_DEGREE_0_COEF_0"), "lacks the attribute"),
    "scale as VEC4": (_acc(SCALE, type="VEC4"), "accessor of type 'VEC4'"),
    "SH as bytes": (_acc(f"{EXTENSION}:SH_DEGREE_0_COEF_0", componentType=5121, normalized=True),
                    "unsigned byte normalized; the spec allows float"),
    "opacity as float normalized": (_acc(OPA, normalized=True), "float normalized"),
    "count mismatch": (_acc(OPA, count=3), "3 OPACITY values for 60 splats"),
    "huge count": (_mutate(lambda doc, blob: [a.update(count=2 ** 40) for a in doc["accessors"]]),
                   "promises 1099511627776 POSITION values"),
    "count zero": (_acc("POSITION", count=0), "count 0"),
    "count string": (_acc("POSITION", count="60"), "count '60'"),
    "sparse": (_acc(ROT, sparse={"count": 1}), "sparse accessor"),
    "no bufferView": (_mutate(lambda doc, blob: _attr(doc, SCALE).pop("bufferView")), "no bufferView"),
    "accessor out of range": (_mutate(lambda doc, blob: doc["meshes"][0]["primitives"][0]["attributes"].update(
        {SCALE: 999})), r"accessors\[999\]"),
    "view past buffer": (_mutate(lambda doc, blob: doc["bufferViews"][0].update(byteOffset=10 ** 8)),
                         "past the end of its"),
    "buffer longer than chunk": (_mutate(lambda doc, blob: doc["buffers"][0].update(byteLength=10 ** 9)),
                                 "declares a buffer of"),
    "external buffer": (_mutate(lambda doc, blob: doc["buffers"][0].update(uri="../../etc/passwd")),
                        "outside the GLB's binary chunk"),
    "odd stride": (_mutate(lambda doc, blob: doc["bufferViews"][0].update(byteStride=4)), "byteStride of 4"),
    "NaN position": (_set_values("POSITION", 5, [0.0, float("nan"), 0.0]), "1 POSITION value.s. that are NaN"),
    "infinite SH": (_set_values(f"{EXTENSION}:SH_DEGREE_0_COEF_0", 0, [float("inf"), 0, 0]), "NaN or infinite"),
    "negative scale": (_set_values(SCALE, 7, [0.1, -0.2, 0.0]), "1 negative scale"),
    "non-unit quaternion": (_set_values(ROT, 2, [0.0, 0.0, 0.0, 0.5]), "not unit quaternions .splat 2 has length 0.5"),
    "zero quaternion": (_set_values(ROT, 0, [0.0, 0.0, 0.0, 0.0]), "not unit quaternions"),
    "opacity above 1": (_set_values(OPA, 4, 1.5), "opacities outside 0..1 .e.g. 1.5"),
    "all transparent": (_set_values(OPA, slice(None), 0.0), "opacity below 1/255"),
    "partial SH degree": (_drop(f"{EXTENSION}:SH_DEGREE_1_COEF_2"), "SH degree 1 partially"),
    "degree 2 without 1": (_mutate(lambda doc, blob: [doc["meshes"][0]["primitives"][0]["attributes"].pop(
        f"{EXTENSION}:SH_DEGREE_1_COEF_{c}") for c in range(3)]), "SH degree 2 without degree 1"),
    "surfel with thickness": (_set_values(SCALE, 1, [0.1, 0.1, 0.05]), "third scale above 0"),
    "node loop": (_mutate(lambda doc, blob: doc.update(nodes=[{"mesh": 0, "children": [0]}])), "loops"),
    "node NaN matrix": (_mutate(lambda doc, blob: doc["nodes"][0].update(matrix=[float("nan")] * 16)),
                        "matrix is not 16 finite numbers"),
    "flattening node": (_mutate(lambda doc, blob: doc["nodes"][0].update(scale=[1, 0, 1])), "determinant 0"),
    "scene out of range": (_mutate(lambda doc, blob: doc.update(scene=7)), r"scenes\[7\]"),
    "component type list": (_acc(SCALE, componentType=[5126]), r"as component type \[5126\]"),
    "bool index": (_mutate(lambda doc, blob: doc["meshes"][0]["primitives"][0]["attributes"].update(
        POSITION=True)), r"accessors\[True\]"),
}

@pytest.fixture(scope="module")
def good_glb():
    return glb_splat_bytes(random_2dgs(n=60, degree=2))


@pytest.mark.parametrize("case", list(HOSTILE))
def test_damaged_and_hostile_files_are_named_errors(good_glb, tmp_path, case):
    make, message = HOSTILE[case]
    path = tmp_path / "bad.glb"
    path.write_bytes(make(good_glb))
    with pytest.raises(SplatzooError, match=message) as err:
        read_glb_splats(path)
    assert str(path) in str(err.value), err.value


def test_mutated_files_never_crash(good_glb, tmp_path):
    """Bytes flipped in the JSON or the binary chunk, or cut off: each file reads, or ends in a SplatzooError."""
    rng = np.random.default_rng(7)
    doc_end = 20 + struct.unpack_from("<I", good_glb, 12)[0]
    path = tmp_path / "mutated.glb"
    outcomes = {"read": 0, "refused": 0}
    for _ in range(150):
        data = bytearray(good_glb)
        kind = rng.integers(3)
        if kind == 2:
            data = data[:rng.integers(len(data))]
        else:
            lo, hi = (12, doc_end) if kind == 0 else (doc_end, len(data))
            for i in rng.integers(lo, hi, rng.integers(1, 4)):
                data[i] = rng.integers(256)
        path.write_bytes(bytes(data))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                read_glb_splats(path)
            outcomes["read"] += 1
        except SplatzooError:
            outcomes["refused"] += 1
    assert outcomes["read"] and outcomes["refused"], outcomes


def test_missing_and_unreadable_paths(tmp_path):
    with pytest.raises(SplatzooError, match="no glTF file at"):
        read_glb_splats(tmp_path / "missing.glb")
    with pytest.raises(SplatzooError, match="no glTF file at"):
        read_glb_splats(tmp_path)
    assert not is_glb(tmp_path / "missing.glb")


# --- the Khronos glTF validator --------------------------------------------------------------------------------

def validate(path) -> dict:
    """The Khronos glTF validator's report on `path` (tools/gltf-validator, through Node.js), or a skip."""
    node = shutil.which("node")
    reason = ("Node.js is not installed" if node is None else
              None if (VALIDATOR / "node_modules" / "gltf-validator" / "package.json").exists() else
              "the glTF validator is not installed: run npm ci --prefix tools/gltf-validator")
    if reason:
        if os.environ.get("SPLATZOO_REQUIRE_BROWSER"):
            pytest.fail(reason)
        pytest.skip(reason)
    out = subprocess.run([node, str(VALIDATOR / "validate.js"), str(path)], capture_output=True, text=True,
                         check=False, timeout=120)
    line = json.loads(out.stdout.strip().splitlines()[-1])
    assert "report" in line, line
    return line["report"]


# The validator (2.0.0-dev.3.10) does not know KHR_gaussian_splatting yet: it says so (UNSUPPORTED_EXTENSION, an
# info), and reports every attribute semantic prefixed with an extension's name as MESH_PRIMITIVE_INVALID_ATTRIBUTE,
# an error, as glTF 2.0 itself allowed only its own names and "_"-prefixed ones (KhronosGroup/glTF-Validator issue
# 252; the spec change is KhronosGroup/glTF pull request 2514). Those errors are the extension's own names; any other
# issue fails.
def unexplained(report) -> list[dict]:
    return [m for m in report["issues"]["messages"] if m["severity"] <= 1 and not (
        m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE"
        and m["pointer"].startswith(f"/meshes/0/primitives/0/attributes/{EXTENSION}:"))]


def test_khronos_validator_finds_nothing_else(tmp_path):
    model = random_2dgs(degree=3)
    path = write_glb_splats(model, tmp_path / "model.glb")
    report = validate(path)
    issues = report["issues"]
    print(f"\nglTF validator {report['validatorVersion']}: {issues['numErrors']} errors, {issues['numWarnings']} "
          f"warnings, {issues['numInfos']} infos, {issues['numHints']} hints")
    for m in issues["messages"]:
        print(f"  {m['severity']} {m['code']} {m.get('pointer', '')}: {m['message']}")
    assert not unexplained(report)
    assert issues["numWarnings"] == 0
    assert issues["numErrors"] == 19  # the 19 extension attributes of SH degree 3 (ROTATION, SCALE, OPACITY, 16 SH)
    codes = {m["code"] for m in issues["messages"] if m["severity"] == 2}
    assert codes == {"UNSUPPORTED_EXTENSION"}
    assert report["info"]["totalVertexCount"] == 60 and report["info"]["drawCallCount"] == 1
    # the same file with the extension's semantics given application names ("_" prefix): not one issue but the
    # unknown extensions, so the errors above are the names and nothing else
    doc, blob = glb_parts(path.read_bytes())
    attrs = doc["meshes"][0]["primitives"][0]["attributes"]
    doc["meshes"][0]["primitives"][0]["attributes"] = {("_" + k.split(":")[1] if ":" in k else k): v
                                                       for k, v in attrs.items()}
    renamed = tmp_path / "renamed.glb"
    renamed.write_bytes(pack(doc, blob))
    issues = validate(renamed)["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    # a damaged file is caught by the validator too (the check works)
    (tmp_path / "bad.glb").write_bytes(HOSTILE["view past buffer"][0](path.read_bytes()))
    assert unexplained(validate(tmp_path / "bad.glb"))


# --- PlayCanvas, a real reader of KHR_gaussian_splatting -------------------------------------------------------

@pytest.fixture(scope="module")
def playcanvas():
    reason = bv.missing(bv.GLTF_PACKAGES)
    if reason:
        if os.environ.get("SPLATZOO_REQUIRE_BROWSER"):
            pytest.fail(reason)
        pytest.skip(reason)
    with bv.BrowserViewers(packages=bv.GLTF_PACKAGES) as b:
        yield b


def surfel_model(means, normals, sigma, opacity, color):
    model = create_model("2dgs", points=means.float(), colors=color.float())
    with torch.no_grad():
        model.means.copy_(means)
        model.quats.copy_(normals_to_quats(normals.double()).float())
        model.log_scales.copy_(torch.log(sigma.float())[:, None].expand(-1, 2))
        model.logit_opacity.copy_(torch.logit(opacity.float()))
        model.sh_dc.copy_(rgb_to_sh0(color.float())[:, None])
    return model


def test_playcanvas_lands_the_surfels_on_their_pixels(playcanvas, tmp_path):
    """Two small surfels at known sub-pixel positions of a turned, non-square camera with an off-centre principal
    point and fx != fy: in PlayCanvas their centroids are where splatzoo puts them, the background comes back exactly
    and the peak colour follows the engine's rule (0.3 px^2 added, opacity kept, its Gaussian cut at 2 sqrt(2) sigma
    and lowered to reach 0 there)."""
    W, H = 80, 60
    base = Camera.look_at([1.0, -0.7, -3.5], [0.1, 0.2, 0.0], width=W, height=H, fov_deg=50)
    K = base.K.clone().double()
    K[0, 2], K[1, 2], K[1, 1] = 0.3 * W, 0.65 * H, 1.1 * K[1, 1]
    cam = Camera(base.world_to_camera.double(), K, W, H)
    targets = [(23.25, 41.5), (60.5, 12.75)]
    c2w = torch.linalg.inv(cam.world_to_camera)
    rays = torch.linalg.solve(K, torch.tensor([[u, v, 1.0] for u, v in targets], dtype=torch.float64).T)
    means = (c2w[:3, :3] @ (3.0 * rays) + c2w[:3, 3:]).T
    normals = (c2w[:3, :3] @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)).expand(2, 3)
    model = surfel_model(means, normals, torch.full((2,), 1.5 * 3.0 / float(K[0, 0])), torch.full((2,), 0.9),
                         torch.tensor([[0.1, 0.9, 0.2]]).expand(2, 3))
    glb = write_glb_splats(model, tmp_path / "two.glb")
    bg = (0.2, 0.4, 0.6)
    img = playcanvas.render_gltf(glb, cam, background=bg)
    weight = np.abs(img - np.array(bg)).sum(-1)
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    var = np.array([1.5 ** 2, 1.65 ** 2]) + 0.3
    e4 = math.exp(-4)
    for (u, v), s2 in zip(targets, var):
        near = (np.abs(xs - u) < 8) & (np.abs(ys - v) < 8)
        w = weight * near
        centroid = np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()
        assert np.abs(centroid - [u, v]).max() < 0.05, centroid
        alpha = 0.9 * (math.exp(-0.5 * 0.25 ** 2 / s2) - e4) / (1 - e4)
        assert abs(img[..., 1][near].max() - (bg[1] * (1 - alpha) + 0.9 * alpha)) < 0.01
    assert np.abs(img[:20, :10] - np.array(bg)).max() <= 0.5 / 255 + 1e-9  # no colour management


def test_playcanvas_draws_the_view_dependent_colour(playcanvas, tmp_path):
    """SH of degree 3 through the file and the engine: PlayCanvas draws splatzoo's colours, and far from what it
    would draw without the view-dependent terms."""
    cam = Camera.look_at([0.4, -0.3, -3.0], [0.0, 0.0, 0.0], width=64, height=64, fov_deg=50)
    g = torch.Generator().manual_seed(3)
    n = 24
    means = torch.stack(torch.meshgrid(torch.linspace(-0.8, 0.8, 6), torch.linspace(-0.6, 0.6, 4), indexing="ij"),
                        -1).reshape(n, 2)
    means = torch.cat([means, torch.zeros(n, 1)], 1).double()
    model = surfel_model(means, torch.tensor([[0.0, 0.0, -1.0]]).expand(n, 3), torch.full((n,), 0.12),
                         torch.full((n,), 0.95), torch.full((n, 3), 0.5))
    sh = create_model("2dgs", points=means.float(), colors=torch.rand(n, 3), sh_degree=3)
    sh.load_state_dict({**model.state_dict(), "sh_rest": torch.randn(n, 15, 3, generator=g) * 0.25})
    plain = write_glb_splats(model, tmp_path / "plain.glb")
    glb = write_glb_splats(sh, tmp_path / "sh.glb")
    own = np.clip(render(sh, cam), 0, 1)
    img = playcanvas.render_gltf(glb, cam)
    without = playcanvas.render_gltf(plain, cam)
    print(f"\nPlayCanvas SH 3 vs splatzoo {bv.psnr(img, own):.2f} dB; without the SH {bv.psnr(without, own):.2f} dB")
    assert bv.psnr(img, own) >= 30.0 and bv.psnr(img, own) > bv.psnr(without, own) + 8


def test_playcanvas_draws_the_2dgs_export_as_splatzoo(playcanvas, trained_2dgs, tmp_path):
    """The target: the 2dgs export, read by PlayCanvas's own glb parser and drawn by its splat renderer with its
    default settings, scores within 2 dB of splatzoo's own render against the ground truth."""
    model, view, _ = trained_2dgs
    glb = write_glb_splats(model, tmp_path / "model.glb")
    gt = view.image_float().double().numpy()
    own = np.clip(render(model, view.camera), 0, 1)
    own_gt = bv.psnr(own, gt)
    img = playcanvas.render_gltf(glb, view.camera)
    vs_own, vs_gt = bv.psnr(img, own), bv.psnr(img, gt)
    print(f"\nsplatzoo vs ground truth {own_gt:.2f} dB; PlayCanvas: vs splatzoo {vs_own:.2f} dB, "
          f"vs ground truth {vs_gt:.2f} dB")
    assert vs_gt >= own_gt - 2.0, (vs_gt, own_gt)
    assert vs_own >= 28.0, vs_own


def test_playcanvas_errors_name_the_file(playcanvas, tmp_path):
    cam = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], width=32, height=32, fov_deg=60)
    with pytest.raises(SplatzooError, match="no glTF file at"):
        playcanvas.render_gltf(tmp_path / "missing.glb", cam)
    with pytest.raises(SplatzooError, match="unknown glTF viewer 'cesium'; known: playcanvas"):
        playcanvas.render_gltf(tmp_path / "missing.glb", cam, viewer="cesium")
    doc, blob = glb_parts(glb_splat_bytes(random_2dgs(n=4, degree=0)))
    doc["meshes"][0]["primitives"][0].pop("extensions")
    mesh = tmp_path / "points.glb"
    mesh.write_bytes(pack(doc, blob))
    with pytest.raises(SplatzooError, match=r"playcanvas failed to render .*points\.glb: .*no Gaussian splats"):
        playcanvas.render_gltf(mesh, cam)


def test_export_command_and_load_model_read_the_glb_back(tmp_path):
    """`splatzoo export FILE --format glb-splat` writes the file and `splatzoo.load_model` (every model format) reads
    it back as the surfels written."""
    import splatzoo
    from typer.testing import CliRunner

    from splatzoo.cli import app

    model = random_2dgs(degree=1)
    splatzoo.save_model(model, tmp_path / "m.pt")
    res = CliRunner().invoke(app, ["export", str(tmp_path / "m.pt"), "--format", "glb-splat", "--out",
                                   str(tmp_path / "m.glb")])
    assert res.exit_code == 0, res.output
    back = splatzoo.load_model(tmp_path / "m.glb")
    assert back.name == "2dgs" and back.num_primitives == model.num_primitives
    a = model.render(CAMERA, backend="reference").rgb
    b = back.render(CAMERA, backend="reference").rgb
    assert float((a - b).abs().max()) < 1e-4
    assert splatzoo.open_model(tmp_path / "m.glb").format == "glb-splat"
