"""A splatzoo PLY export in real third-party splat viewers (Spark, GaussianSplats3D) in headless Chromium: the camera
lands every splat on its pixel, and a trained 2DGS model's export, seen with each viewer's default settings, scores
within 2 dB of splatzoo's own render against the ground truth."""
import os

import numpy as np
import pytest
import torch

from splatzoo import Camera, create_model
from splatzoo.export import save_ply
from splatzoo.geometry import normals_to_quats, rgb_to_sh0

import browser_viewers as bv


@pytest.fixture(scope="module")
def browser():
    reason = bv.missing()
    if reason:
        if os.environ.get("SPLATZOO_REQUIRE_BROWSER"):
            pytest.fail(reason)
        pytest.skip(reason)
    with bv.BrowserViewers() as b:
        yield b


def surfel_model(means, normals, sigma, opacity, color):
    """A 2dgs model with exactly these surfels (means [N,3], normals [N,3], sigma [N] world units, opacity [N],
    color [N,3])."""
    model = create_model("2dgs", points=means.float(), colors=color.float())
    with torch.no_grad():
        model.means.copy_(means)
        model.quats.copy_(normals_to_quats(normals.double()).float())
        model.log_scales.copy_(torch.log(sigma.float())[:, None].expand(-1, 2))
        model.logit_opacity.copy_(torch.logit(opacity.float()))
        model.sh_dc.copy_(rgb_to_sh0(color.float())[:, None])
    return model


def test_splats_land_on_their_pixels(browser, tmp_path):
    """Two small surfels placed to project at known sub-pixel positions of a turned, non-square camera with an
    off-centre principal point and fx != fy: in each viewer their centroids are where splatzoo puts them, the
    background colour comes back exactly, and the peak colour follows the viewer's dilation rule."""
    W, H = 80, 60
    base = Camera.look_at([1.0, -0.7, -3.5], [0.1, 0.2, 0.0], width=W, height=H, fov_deg=50)
    K = base.K.clone().double()
    K[0, 2], K[1, 2], K[1, 1] = 0.3 * W, 0.65 * H, 1.1 * K[1, 1]
    cam = Camera(base.world_to_camera.double(), K, W, H)
    targets = [(23.25, 41.5), (60.5, 12.75)]
    # GaussianSplats3D 0.4.7 loses splats of a scene of only a handful: 30 more lie off-screen to the left
    pixels = targets + [(-40.0 - 3 * i, 30.0) for i in range(30)]
    c2w = torch.linalg.inv(cam.world_to_camera)
    rays = torch.linalg.solve(K, torch.tensor([[u, v, 1.0] for u, v in pixels], dtype=torch.float64).T)
    means = (c2w[:3, :3] @ (3.0 * rays) + c2w[:3, 3:]).T  # at camera depth 3
    normals = (c2w[:3, :3] @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)).expand(len(pixels), 3)
    n = len(pixels)
    model = surfel_model(means, normals, torch.full((n,), 1.5 * 3.0 / float(K[0, 0])), torch.full((n,), 0.9),
                         torch.tensor([[0.1, 0.9, 0.2]]).expand(n, 3))
    ply = save_ply(model, tmp_path / "two.ply")
    bg = (0.2, 0.4, 0.6)

    def centroids_and_peaks(img):
        weight = np.abs(img - np.array(bg)).sum(-1)
        ys, xs = np.mgrid[0:H, 0:W] + 0.5  # pixel centres
        centroids, peaks = [], []
        for u, v in targets:
            near = (np.abs(xs - u) < 8) & (np.abs(ys - v) < 8)
            w = weight * near
            centroids.append(((w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()))
            peaks.append(img[..., 1][near].max())
        return np.array(centroids), np.array(peaks)

    # the brightest pixel centre lies 0.25 px from each surfel's centre, along x for the first (sigma 1.5 px), along y
    # for the second (sigma 1.65 px: fy = 1.1 fx); green there: bg (1 - a) + 0.9 a, with a by each renderer's rule
    var = np.array([1.5 ** 2, 1.65 ** 2])
    other = var[::-1]

    def green(a):
        return bg[1] * (1 - a) + 0.9 * a

    dilated = var + 0.3  # both viewers add 0.3 px^2 to the screen covariance
    expected = {
        "splatzoo": green(0.9 * np.exp(-0.5 * 0.25 ** 2 / var)),
        "gs3d": green(0.9 * np.exp(-0.5 * 0.25 ** 2 / dilated)),  # opacity kept (3DGS's rule)
        "spark": green(0.9 * np.sqrt(var * other / (dilated * (other + 0.3)))  # opacity rescaled (Mip-Splatting's)
                       * np.exp(-0.5 * 0.25 ** 2 / dilated)),
    }
    with torch.no_grad():
        ref = model.render(cam, background=torch.tensor(bg), backend="cpu").rgb.double().numpy()
    c, peaks = centroids_and_peaks(ref)
    assert np.abs(c - np.array(targets)).max() < 0.01
    assert np.abs(peaks - expected["splatzoo"]).max() < 0.002, peaks
    for viewer in bv.VIEWERS:
        img = browser.render(ply, cam, viewer=viewer, background=bg)
        c, peaks = centroids_and_peaks(img)
        assert np.abs(c - np.array(targets)).max() < 0.1, (viewer, c)  # Spark stores centres as float16
        far = (slice(0, 20), slice(0, 10))
        assert np.abs(img[far] - np.array(bg)).max() <= 0.5 / 255 + 1e-9, viewer  # no colour management
        assert np.abs(peaks - expected[viewer]).max() < 0.01, (viewer, peaks, expected[viewer])


@pytest.fixture(scope="module")
def trained_2dgs_ply(trained_2dgs, tmp_path_factory):
    """The PLY export of the trained_2dgs model (tests/conftest.py)."""
    return save_ply(trained_2dgs[0], tmp_path_factory.mktemp("browser_viewers") / "2dgs.ply")


def test_2dgs_export_in_viewers_matches_splatzoo(browser, trained_2dgs, trained_2dgs_ply):
    """The target: a 2dgs export rendered by a third-party viewer with its default settings scores within 2 dB of
    splatzoo's own render against the ground truth. Both viewers draw each surfel as a screen-space Gaussian (an
    affine projection, 8-bit colours, their own 0.3 px^2 dilation: Spark rescales the opacity, GS3D does not) where
    splatzoo intersects rays with the surfel. This small model is coarse, so the dilation costs little here and both
    stay above 25 dB from splatzoo's render; on a finer model GS3D's default loses more (about 2.8 dB at 25.5 dB, see
    benchmarks/bench_browser_viewers.py)."""
    (model, view, _), ply = trained_2dgs, trained_2dgs_ply
    bg = (1.0, 1.0, 1.0)
    gt = view.image_float().double().numpy()
    with torch.no_grad():
        own = model.render(view.camera, background=torch.tensor(bg), backend="cpu").rgb.clamp(0, 1).double().numpy()
    own_gt = bv.psnr(own, gt)
    print(f"\nsplatzoo vs ground truth {own_gt:.2f} dB")
    for viewer in bv.VIEWERS:
        img = browser.render(ply, view.camera, viewer=viewer, background=bg)
        vs_own, vs_gt = bv.psnr(img, own), bv.psnr(img, gt)
        print(f"{viewer}: vs splatzoo {vs_own:.2f} dB, vs ground truth {vs_gt:.2f} dB")
        assert vs_gt >= own_gt - 2.0, (viewer, vs_gt, own_gt)
        assert vs_own >= 25.0, (viewer, vs_own)


# the settings with which each viewer draws what splatzoo's anti-aliased render draws: a Mip-Splatting dilation of
# splatzoo's pixel footprint (0.1 px^2, opacity rescaled) and, for Spark, splats sorted by depth as splatzoo does
MATCHED = {"spark": {"blurAmount": 0.1, "sortRadial": False}, "gs3d": {"antialiased": True, "kernel2DSize": 0.1}}


def test_matched_viewer_settings_draw_splatzoo_render(browser, trained_2dgs, trained_2dgs_ply):
    (model, view, _), ply = trained_2dgs, trained_2dgs_ply
    assert model.antialias  # the training default
    with torch.no_grad():
        own = model.render(view.camera, background=torch.ones(3), backend="cpu").rgb.clamp(0, 1).double().numpy()
    for viewer, options in MATCHED.items():
        default = bv.psnr(browser.render(ply, view.camera, viewer=viewer), own)
        matched = bv.psnr(browser.render(ply, view.camera, viewer=viewer, options=options), own)
        print(f"\n{viewer} vs splatzoo: default {default:.2f} dB, matched {matched:.2f} dB")
        assert matched >= 38.0 and matched > default + 1.0, (viewer, default, matched)


def test_errors_name_the_viewer_and_the_file(browser, tmp_path):
    cam = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], width=32, height=32, fov_deg=60)
    with pytest.raises(bv.SplatzooError, match="unknown viewer 'supersplat'; known: spark, gs3d"):
        browser.render(tmp_path / "x.ply", cam, viewer="supersplat")
    with pytest.raises(bv.SplatzooError, match="no PLY file at"):
        browser.render(tmp_path / "missing.ply", cam, viewer="spark")
    broken = tmp_path / "broken.ply"  # a vertex without y: Spark's reader refuses it, and the page says so
    broken.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n"
                       + bytes(4))
    with pytest.raises(bv.SplatzooError, match=r"spark failed to render .*broken\.ply: .*Missing y"):
        browser.render(broken, cam, viewer="spark")


def test_threejs_reads_the_mesh_files(browser, tmp_path):
    """The textured GLB and OBJ (+ MTL + PNG) that `splatzoo export --format mesh-glb/mesh-obj` and `extract-mesh`
    write load in three.js's own GLTFLoader and OBJLoader + MTLLoader: every triangle, the UVs, and the texture."""
    import open3d as o3d

    from splatzoo.mesh import write_mesh
    from splatzoo.errors import SplatzooError
    from splatzoo.mesh_texture import TexturedMesh, uv_atlas, write_textured_mesh

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=8)
    sphere.compute_vertex_normals()
    positions = np.asarray(sphere.vertices, dtype=np.float32)
    faces = np.asarray(sphere.triangles, dtype=np.int64)
    vmapping, atlas_faces, uvs = uv_atlas(positions, faces, 64, 2)
    texture = np.zeros((64, 64, 3), np.uint8)
    texture[..., 0], texture[::8, :, 1] = 200, 255  # red with green lines: a mean colour to find again
    mesh = TexturedMesh(positions[vmapping], atlas_faces, uvs=uvs, texture=texture)
    glb = write_textured_mesh(mesh, tmp_path / "textured.glb")
    obj = write_textured_mesh(mesh, tmp_path / "textured.obj")
    sphere.vertex_colors = o3d.utility.Vector3dVector(np.full((len(sphere.vertices), 3), 0.5))
    plain = write_mesh(sphere, tmp_path / "plain.glb")
    want = texture.reshape(-1, 3).mean(0) / 255
    for path in (glb, obj):
        got = browser.load_mesh(path)
        assert got["triangles"] == len(atlas_faces) and got["uvs"], (path.name, got)
        assert got["textured"] and got["textureSize"] == [64, 64], (path.name, got)
        assert np.allclose(got["meanTexel"], want, atol=2 / 255), (path.name, got["meanTexel"], want)
    got = browser.load_mesh(plain)
    assert got["triangles"] == len(faces) and not got["textured"]
    with pytest.raises(SplatzooError, match="no mesh file"):
        browser.load_mesh(tmp_path / "missing.glb")


def test_viewers_open_the_compressed_exports(browser, trained_2dgs, trained_2dgs_ply, tmp_path):
    """`splatzoo export --format spz` and `sog` (through splat-transform) open in Spark and draw what the PLY draws,
    up to the formats' quantisation. (SPZ version 4, gzip-free, is refused by Spark 2.2: "Invalid gzip header"; the
    default is 3.)"""
    from splatzoo.errors import SplatzooError
    from splatzoo.export import export
    from splatzoo.splat_tools import find_splat_transform

    try:
        find_splat_transform()
    except SplatzooError as e:
        if os.environ.get("SPLATZOO_REQUIRE_BROWSER"):
            pytest.fail(str(e))
        pytest.skip(str(e))

    (model, view, _), ply = trained_2dgs, trained_2dgs_ply
    # (GaussianSplats3D 0.4.7 reads no SOG, and never finishes loading an SPZ from splat-transform: not tested)
    for viewer, formats in (("spark", ("spz", "sog")),):
        reference = browser.render(ply, view.camera, viewer=viewer)
        for fmt in formats:
            path = export(ply, tmp_path / f"model.{fmt}", fmt)
            img = browser.render(path, view.camera, viewer=viewer)
            print(f"\n{viewer} {fmt} vs {viewer} ply: {bv.psnr(img, reference):.2f} dB")
            assert bv.psnr(img, reference) >= 30.0, (viewer, fmt)
