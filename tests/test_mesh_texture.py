"""Textured mesh export: the baked texture beats vertex colours on a striped surface; the GLB and OBJ files are
well formed and readable by open3d, trimesh and pygltflib; options and outputs are checked."""
import json
import struct

import numpy as np
import pytest
import torch

from splatzoo import Camera, create_model
from splatzoo.errors import SplatzooError
from splatzoo.mesh import extract_mesh, write_mesh
from splatzoo.mesh_texture import (TexturedMesh, TexturedMeshOptions, export_textured_mesh, make_options,
                                   render_mesh, texture_mesh, write_glb, write_obj)

STRIPE_PERIOD = 0.25  # world units: about 10 pixels in the 64-pixel views
RADIUS = 0.8


def _ring(n, size=64, elevation=0.4, phase=0.0):
    return [Camera.look_at([2.8 * np.cos(a), 2.8 * np.sin(a), elevation], [0, 0, 0], up=(0, 0, 1), width=size,
                           height=size, fov_deg=40, dtype=torch.float32)
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False) + phase]


def striped_sphere(n=4000):
    """An opaque 2DGS sphere painted with sharp horizontal red/white stripes."""
    g = torch.Generator().manual_seed(0)
    d = torch.randn(n, 3, generator=g)
    pts = RADIUS * d / d.norm(dim=1, keepdim=True)
    red = torch.remainder(pts[:, 2], STRIPE_PERIOD) < STRIPE_PERIOD / 2
    colors = torch.where(red[:, None], torch.tensor([0.9, 0.1, 0.1]), torch.tensor([0.95, 0.95, 0.95]))
    model = create_model("2dgs", pts, colors)
    with torch.no_grad():
        model.logit_opacity.fill_(6.0)
    return model


@pytest.fixture(scope="module")
def baked():
    return _bake()


def _bake():
    """The striped sphere meshed with voxels a third of a stripe period wide (vertex colours blur the stripes),
    then textured from 12 views."""
    model = striped_sphere()
    cams = _ring(8, elevation=0.4) + _ring(4, elevation=-0.8, phase=0.4)
    voxel = STRIPE_PERIOD / 3
    mesh, params, _ = extract_mesh(model, cams, voxel_size=voxel, sdf_trunc=3 * voxel)
    tex = texture_mesh(mesh, model, cams, TexturedMeshOptions(texture_size=256, padding=2))
    return model, mesh, tex


def assert_same_vertices(a, b, atol):
    """The two meshes hold the same (position, colour) vertices, in any order.

    A reader may order vertices its own way, and a sort of float rows is no fix: two vertices whose first
    coordinates differ by less than a text format's rounding swap places, and which ones do depends on the mesh,
    which TSDF fusion does not make bit-identical from one machine to the next. So each vertex of one mesh is
    matched to its nearest in the other, both ways, and the pairs must agree within atol."""
    from scipy.spatial import cKDTree

    rows_a, rows_b = ([np.concatenate([np.asarray(m.vertices), np.asarray(m.vertex_colors)], 1) for m in (a, b)])
    assert rows_a.shape == rows_b.shape
    for x, y in ((rows_a, rows_b), (rows_b, rows_a)):
        _, nearest = cKDTree(y).query(x)
        worst = np.abs(x - y[nearest]).max(1)
        assert (worst <= atol).all(), f"{(worst > atol).sum()} vertices without a match within {atol}: {worst.max()}"


def _psnr(a, b, mask):
    return 10 * np.log10(1 / max(float(((a[mask] - b[mask]) ** 2).mean()), 1e-12))


def test_texture_renders_closer_to_the_model_than_vertex_colours(baked):
    model, mesh, tex = baked
    assert tex.texture.shape == (256, 256, 3) and tex.info["surface_seen"] > 0.9
    vc = TexturedMesh.from_open3d(mesh)
    gains = []
    for cam in _ring(3, elevation=0.1, phase=0.25):   # views between the baking views
        with torch.no_grad():
            ref = model.render(cam, background=torch.zeros(3), image_only=True)
        ref_img, alpha = ref.rgb.clamp(0, 1).numpy(), ref.alpha.numpy() >= 0.5
        img_t, hit_t = render_mesh(tex, cam)
        img_v, hit_v = render_mesh(vc, cam)
        mask = alpha & hit_t & hit_v
        assert mask.sum() > 300
        gains.append(_psnr(img_t, ref_img, mask) - _psnr(img_v, ref_img, mask))
        assert _psnr(img_t, ref_img, mask) > 16.5
    assert min(gains) > 1.5, gains


def _glb_json_and_blob(data: bytes):
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert magic == 0x46546C67 and version == 2 and length == len(data)
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942
    return doc, data[28 + jlen:28 + jlen + blen]


_COMPONENTS = {5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}


def _check_glb_layout(data: bytes):
    """One buffer in the binary chunk (no URI anywhere), every accessor's min/max equal to its data."""
    doc, blob = _glb_json_and_blob(data)
    assert len(doc["buffers"]) == 1 and "uri" not in doc["buffers"][0]
    assert doc["buffers"][0]["byteLength"] <= len(blob)
    assert "data:" not in json.dumps(doc)
    for acc in doc["accessors"]:
        view = doc["bufferViews"][acc["bufferView"]]
        assert view["buffer"] == 0 and view["byteOffset"] % 4 == 0
        a = np.frombuffer(blob, _COMPONENTS[acc["componentType"]], acc["count"] * _WIDTH[acc["type"]],
                          view["byteOffset"] + acc.get("byteOffset", 0)).reshape(acc["count"], -1)
        assert acc["min"] == pytest.approx(a.min(0).tolist()) and acc["max"] == pytest.approx(a.max(0).tolist())
    return doc, blob


def test_glb_is_one_binary_buffer_with_exact_bounds_and_reads_everywhere(baked, tmp_path):
    import open3d as o3d
    import pygltflib
    import trimesh

    _, _, tex = baked
    path = write_glb(tex, tmp_path / "mesh.glb")
    doc, blob = _check_glb_layout(path.read_bytes())
    prim = doc["meshes"][0]["primitives"][0]
    assert set(prim["attributes"]) == {"POSITION", "NORMAL", "TEXCOORD_0"}
    assert doc["accessors"][prim["indices"]]["max"] == [len(tex.positions) - 1]
    image = doc["images"][0]
    assert image["mimeType"] == "image/png" and "uri" not in image
    view = doc["bufferViews"][image["bufferView"]]
    assert blob[view["byteOffset"]:view["byteOffset"] + 8] == b"\x89PNG\r\n\x1a\n"
    material = doc["materials"][0]
    assert material["pbrMetallicRoughness"]["baseColorTexture"]["index"] == 0
    assert "KHR_materials_unlit" in material["extensions"] and "KHR_materials_unlit" in doc["extensionsUsed"]
    assert "extensionsRequired" not in doc
    assert list(tmp_path.iterdir()) == [path]   # no temporary file left behind

    g = pygltflib.GLTF2().load(str(path))
    assert len(g.buffers) == 1 and g.buffers[0].uri is None and len(g.binary_blob()) >= g.buffers[0].byteLength
    m = o3d.io.read_triangle_mesh(str(path))
    assert len(m.triangles) == len(tex.faces) and len(m.vertices) == len(tex.positions)
    t = trimesh.load(path, force="mesh", process=False)
    assert len(t.faces) == len(tex.faces)
    assert np.allclose(np.asarray(t.vertices), tex.positions, atol=1e-6)
    img = np.asarray(t.visual.material.baseColorTexture.convert("RGB"))
    assert np.array_equal(img, tex.texture)
    # trimesh turns glTF's v (down the image) into OBJ's (up): the same texels either way
    assert np.allclose(1 - np.asarray(t.visual.uv)[:, 1], tex.uvs[:, 1], atol=1e-6)


def test_obj_mtl_png_use_relative_names_and_read_back(baked, tmp_path):
    import open3d as o3d
    import trimesh

    _, _, tex = baked
    path = write_obj(tex, tmp_path / "out" / "mesh.obj")
    names = sorted(p.name for p in path.parent.iterdir())
    assert names == ["mesh.mtl", "mesh.obj", "mesh.png"]   # and no temporary file left behind
    text = path.read_text()
    head = text[:200]
    assert "mtllib mesh.mtl" in text and ".mesh.obj." not in text and "tmp" not in head.lower()
    assert "map_Kd mesh.png" in (path.parent / "mesh.mtl").read_text()
    m = o3d.io.read_triangle_mesh(str(path))
    assert len(m.triangles) == len(tex.faces) and m.has_triangle_uvs()
    t = trimesh.load(path, force="mesh", process=False)
    assert len(t.faces) == len(tex.faces)
    img = np.asarray(t.visual.material.image.convert("RGB"))
    assert np.array_equal(img, tex.texture)


def test_write_mesh_obj_and_glb_of_a_vertex_coloured_mesh(baked, tmp_path):
    import open3d as o3d
    import trimesh

    _, mesh, _ = baked
    obj = write_mesh(mesh, tmp_path / "m.obj")
    text = obj.read_text()
    assert ".m.obj." not in text and "object name" not in text
    back = o3d.io.read_triangle_mesh(str(obj))
    assert len(back.triangles) == len(mesh.triangles) and back.has_vertex_colors()

    assert_same_vertices(back, mesh, atol=1e-4)

    glb = write_mesh(mesh, tmp_path / "m.glb")
    doc, _ = _check_glb_layout(glb.read_bytes())
    assert "COLOR_0" in doc["meshes"][0]["primitives"][0]["attributes"]
    back = o3d.io.read_triangle_mesh(str(glb))
    assert len(back.triangles) == len(mesh.triangles)
    assert np.allclose(np.sort(np.asarray(back.vertices), 0), np.sort(np.asarray(mesh.vertices), 0), atol=1e-5)
    t = trimesh.load(glb, force="mesh", process=False)
    assert len(t.faces) == len(mesh.triangles)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.glb", "m.obj"]


def test_vertex_sets_match_whatever_the_order_and_ties():
    """Two vertices whose x differ by less than the write's rounding: a sort of rows pairs them the wrong way
    round once rounded, the nearest-vertex match does not; a vertex really moved still fails."""
    import open3d as o3d

    def mesh(points, colours):
        m = o3d.geometry.TriangleMesh()
        m.vertices, m.vertex_colors = o3d.utility.Vector3dVector(points), o3d.utility.Vector3dVector(colours)
        return m
    pts = np.array([[0.1000004, 0.0, 0.0], [0.1000001, 1.0, 1.0], [0.5, 0.5, 0.5]])
    cols = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    rounded = mesh(np.round(pts, 6)[::-1], cols[::-1])   # as a text file of 6 decimals, read back reversed
    assert_same_vertices(rounded, mesh(pts, cols), atol=1e-4)
    moved = pts.copy()
    moved[2, 1] += 1e-3
    with pytest.raises(AssertionError, match="1 vertices without a match"):
        assert_same_vertices(mesh(moved, cols), mesh(pts, cols), atol=1e-4)


def test_options_are_checked_and_converted():
    assert make_options(texture_size="1024", unlit="false", voxel_size="none").texture_size == 1024
    assert make_options({"sharpness": "2.5"}).sharpness == 2.5
    with pytest.raises(SplatzooError, match="unknown mesh texture option.*texture_siz.*did you mean texture_size"):
        make_options(texture_siz=512)
    with pytest.raises(SplatzooError, match="texture_size"):
        make_options(texture_size=8)
    with pytest.raises(SplatzooError, match="mesh texture: option texture_size expects int, got .big."):
        make_options(texture_size="big")
    with pytest.raises(SplatzooError, match="views.*train, all"):
        make_options(views="test")
    with pytest.raises(SplatzooError, match="max_triangles"):
        make_options(max_triangles=5)
    with pytest.raises(SplatzooError, match="voxel_size"):
        make_options(voxel_size=-1.0)


def test_export_from_a_run(tmp_path):
    """A run folder whose model is the striped sphere (its dataset's cameras look at the origin from 2.8 units):
    export writes a GLB and an OBJ with its material; bad names fail before any work."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig
    from splatzoo.zoo import save_model

    data = make_synthetic_scene("plain", tmp_path / "data", views=9, width=48, height=48)
    run = tmp_path / "run"
    train(data, "2dgs", {}, TrainConfig(iterations=1, backend="cpu", num_primitives=50, densify=False), run,
          progress=False, evaluate_at_end=False)
    save_model(striped_sphere(1500), run / "model.pt")
    said = []
    out = export_textured_mesh(run, tmp_path / "x" / "sphere.glb", progress=said.append, texture_size="128",
                               max_triangles=2000)
    _check_glb_layout(out.read_bytes())
    assert any("texture:" in s for s in said)
    out = export_textured_mesh(run, tmp_path / "x" / "sphere.obj", texture_size=64, views="all")
    assert sorted(p.name for p in out.parent.iterdir()) == ["sphere.glb", "sphere.mtl", "sphere.obj", "sphere.png"]
    with pytest.raises(SplatzooError, match=r"\.glb.*\.obj"):
        export_textured_mesh(run, tmp_path / "sphere.ply")
    with pytest.raises(SplatzooError, match="unknown mesh texture option"):
        export_textured_mesh(run, tmp_path / "sphere.glb", size=3)
    with pytest.raises(SplatzooError, match="does not exist"):
        export_textured_mesh(tmp_path / "nowhere", tmp_path / "sphere.glb")
