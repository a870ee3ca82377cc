"""The web viewer: cameras between viser and splatzoo, render modes, runs side by side, clear errors before a server
starts, and the page in a real (headless) Chromium showing what a direct render of its camera shows."""
import math
import os
import shutil
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from splatzoo import Camera, Surfels, create_model
from splatzoo.errors import SplatzooError
from splatzoo.runs import train
from splatzoo.training import TrainConfig
from splatzoo.model_files import open_model
from splatzoo.viewer import (LiveModel, Source, Viewer, browser_camera, camera_pose, check_address, expand_runs,
                             render_layout, render_frame, surfel_cycles_per_pixel, view, viewer_source)

pytest.importorskip("viser")


@pytest.fixture(scope="module")
def compare_dir(tmp_path_factory):
    """A folder of two small trained runs, as `splatzoo compare` writes them."""
    from splatzoo.data.synthetic import make_synthetic_scene

    root = tmp_path_factory.mktemp("viewer")
    data = make_synthetic_scene("sweater", root / "data", views=8, width=48, height=48)
    cfg = dict(iterations=150, backend="cpu", num_primitives=600, densify=False)
    train(data, "gabor", {"n_waves": 2}, TrainConfig(**cfg), root / "compare" / "gabor", progress=False,
          evaluate_at_end=False)
    train(data, "2dgs", {}, TrainConfig(**cfg), root / "compare" / "2dgs", progress=False, evaluate_at_end=False)
    return root / "compare"


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * math.log10(255 ** 2 / max(mse, 1e-12))


def test_camera_round_trip():
    cam = Camera.look_at([0.3, -0.4, -2.5], [0.1, 0.0, 0.2], width=160, height=120, fov_deg=50)
    pose = camera_pose(cam)
    assert abs(np.linalg.norm(pose["wxyz"]) - 1) < 1e-12 and abs(pose["aspect"] - 4 / 3) < 1e-12
    back = browser_camera(pose["wxyz"], pose["position"], pose["fov"], cam.width, cam.height)
    assert torch.allclose(back.world_to_camera, cam.world_to_camera, atol=1e-10)
    assert torch.allclose(back.K, cam.K, atol=1e-9)
    # a camera turned by 90 degrees about its optical axis: quaternions from every branch of the conversion
    for axis in range(3):
        R = torch.eye(3, dtype=torch.float64)[[1, 2, 0] if axis == 0 else [2, 0, 1] if axis == 1 else [0, 1, 2]]
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = R if torch.det(R) > 0 else -R
        c = Camera(w2c, cam.K, cam.width, cam.height)
        p = camera_pose(c)
        assert torch.allclose(browser_camera(p["wxyz"], p["position"], p["fov"], 160, 120).world_to_camera, w2c,
                              atol=1e-10)


def _cpu_source(path) -> Source:
    """`path` as `splatzoo view` opens it, on the CPU."""
    return viewer_source(open_model(path, backend="cpu", latest=True))


def test_render_modes(compare_dir):
    gabor = _cpu_source(compare_dir / "gabor")
    model, cam = gabor.model(), gabor.views[0].camera
    images = {mode: render_frame(model, cam, mode, backend="cpu")
              for mode in ("rgb", "depth", "normal", "alpha", "surfels", "waves", "frequency")}
    for mode, image in images.items():
        assert image.shape == (48, 48, 3) and image.dtype == np.uint8, mode
        assert image.max() > 0, mode
    assert not np.array_equal(images["rgb"], images["surfels"])
    alpha = images["alpha"][..., 0].astype(float) / 255
    assert alpha[24, 24] > 0.5 and alpha[0, 0] < 0.2 and np.all(images["alpha"][..., 0] == images["alpha"][..., 2])
    # 2DGS has no waves: its wave map is the colour map's zero everywhere a surfel covers
    two = _cpu_source(compare_dir / "2dgs").model()
    waves = render_frame(two, cam, "waves", backend="cpu").astype(float)
    assert waves.max() < 10  # inferno's zero is black
    with pytest.raises(SplatzooError, match="render mode"):
        render_frame(model, cam, "x-ray")


def test_frequency_against_nyquist():
    """A surfel's wave frequency on screen: k radians per sigma, sigma s, depth z, focal f -> k/s * z/f / 2pi
    cycles per pixel."""
    cam = Camera.look_at([0, 0, -4], [0, 0, 0], width=64, height=64, fov_deg=60)
    f = float(cam.K[0, 0])
    s = Surfels(means=torch.zeros(2, 3), quats=torch.tensor([[1.0, 0, 0, 0]] * 2), scales=torch.full((2, 2), 0.2),
                opacities=torch.ones(2), base_color=torch.full((2, 3), 0.5),
                wave_vectors=torch.tensor([[[3.0, 4.0]], [[30.0, 40.0]]]), wave_phases=torch.zeros(2, 1),
                wave_amplitudes=torch.full((2, 1, 3), 0.1))
    cpp = surfel_cycles_per_pixel(s, cam)
    expected = torch.tensor([5.0, 50.0]) / 0.2 * 4 / f / (2 * math.pi)
    assert torch.allclose(cpp, expected, rtol=1e-5)
    s.wave_counts = torch.tensor([0, 1], dtype=torch.int32)  # a pruned wave has no frequency
    assert surfel_cycles_per_pixel(s, cam)[0] == 0


def test_side_by_side_shares_the_camera(compare_dir):
    a, b = _cpu_source(compare_dir / "gabor"), _cpu_source(compare_dir / "2dgs")
    cam = a.views[1].camera.scaled(2.0)  # 96 x 96
    both = render_layout([a.model(), b.model()], cam, "rgb", [a.background, b.background], backend="cpu", gap=2)
    assert both.shape == (96, 96, 3)
    K = cam.K.clone()
    K[0, 2] = 47 / 2
    half = Camera(cam.world_to_camera, K, 47, 96)
    assert np.array_equal(both[:, :47], render_frame(a.model(), half, "rgb", backend="cpu"))
    assert np.array_equal(both[:, 49:96], render_frame(b.model(), half, "rgb", backend="cpu"))
    assert np.all(both[:, 47:49] == 255)


def test_runs_are_checked_before_a_server_starts(compare_dir, tmp_path):
    assert [p.name for p in expand_runs([compare_dir])] == ["2dgs", "gabor"]
    nested = tmp_path / "report"  # the layout `splatzoo compare` writes: OUT/runs/<label>
    shutil.copytree(compare_dir, nested / "runs")
    assert [p.name for p in expand_runs([nested])] == ["2dgs", "gabor"]
    with pytest.raises(SplatzooError, match="does not exist"):
        expand_runs([tmp_path / "missing"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(SplatzooError, match="neither a run folder"):
        expand_runs([tmp_path / "empty"])
    broken = tmp_path / "broken"
    shutil.copytree(compare_dir / "gabor", broken)
    (broken / "model.pt").write_bytes(b"not a model")
    with pytest.raises(SplatzooError, match="model.pt"):
        _cpu_source(broken)
    started = tmp_path / "started"
    started.mkdir()
    shutil.copy(compare_dir / "gabor" / "config.json", started)
    with pytest.raises(SplatzooError, match="no model yet"):
        _cpu_source(started)
    r = subprocess.run([sys.executable, "-m", "splatzoo", "view", str(tmp_path / "missing")], capture_output=True,
                       text=True)
    assert r.returncode == 2 and "does not exist" in r.stderr and "Traceback" not in r.stderr


def test_a_port_in_use_is_a_clear_error():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(SplatzooError, match=f"port {port} on 127.0.0.1 is in use"):
            check_address("127.0.0.1", port)
    with pytest.raises(SplatzooError, match="between 1 and 65535"):
        check_address("127.0.0.1", 70000)


def test_live_model_is_a_copy():
    """Training publishes copies: what the viewer renders does not change under it while the optimiser steps."""
    torch.manual_seed(0)
    net = create_model("gabor", torch.randn(50, 3), torch.rand(50, 3), n_waves=2)
    live = LiveModel(every=10.0)
    assert live.model() is None
    live.publish(net, 3)
    seen = live.model()
    before = seen.means.clone()
    with torch.no_grad():
        net.means.add_(1.0)
    live.publish(net, 4)  # too soon: skipped
    assert live.version == 1 and torch.equal(live.model().means, before)
    live.publish(net, 5, force=True)
    assert live.version == 2 and live.iteration == 5 and torch.allclose(live.model().means, before + 1)
    assert Source("live", live=live).model() is live.model()


def _browser():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    if os.environ.get("SPLATZOO_REQUIRE_BROWSER"):
        pytest.fail("no Chromium found: install it (apt-get install -y chromium)")
    pytest.skip("no Chromium on this machine (apt-get install -y chromium)")


def _settled_screenshot(page, timeout: float = 20.0) -> np.ndarray:
    """The page once two screenshots a moment apart agree (the page fades new images in)."""
    import cv2

    last, deadline = None, time.monotonic() + timeout
    while True:
        time.sleep(0.5)
        shot = cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        if last is not None and np.array_equal(shot, last) or time.monotonic() > deadline:
            return shot
        last = shot


def test_the_page_shows_what_the_camera_sees(compare_dir):
    """Load the page in headless Chromium: the image on the page is a render of the page's own camera (compared with
    a direct render of that camera, not only that the page loads); clicking through to a training camera moves the
    browser's camera there and shows its ground truth; a snapshot is written."""
    sync_playwright = pytest.importorskip("playwright.sync_api").sync_playwright
    executable = _browser()
    viewer = view([compare_dir / "gabor"], port=0, backend="cpu")
    source = viewer.sources[0]
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=executable, args=["--use-angle=swiftshader",
                                                                         "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 640, "height": 480})
            page.goto(viewer.url)
            deadline = time.monotonic() + 60
            while not viewer.sessions and time.monotonic() < deadline:
                time.sleep(0.05)
            session = next(iter(viewer.sessions.values()))
            assert session.full_sent.wait(60), "no full-size frame was rendered for the page"
            viewer.show_cameras(False)  # frustums drawn over the image are not part of the render
            shown = _settled_screenshot(page)
            c = session.client.camera
            cam = browser_camera(c.wxyz, c.position, c.fov, c.image_width, c.image_height)
            assert (cam.width, cam.height) == (640, 480)
            direct = render_frame(source.model(), cam, "rgb", background=source.background, backend="cpu")
            # the control panel (top right), the notice about software WebGL (top left) and the axes (bottom left)
            # cover parts of the page
            region = (slice(260, 480), slice(60, 640))
            assert psnr(shown[region], direct[region]) > 35, psnr(shown[region], direct[region])
            assert direct[region].std() > 5  # the region shows the model, not only background

            # a training camera: the browser's camera goes there (a round trip through the page)
            target = source.views[3]
            session.full_sent.clear()
            session.jump_to(target)
            want = camera_pose(target.camera)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and np.abs(session.client.camera.position - want["position"]).max() > 1e-4:
                time.sleep(0.05)
            assert np.abs(session.client.camera.position - want["position"]).max() < 1e-4
            assert abs(session.client.camera.fov - want["fov"]) < 1e-4
            assert session.truth is not None and target.name in session.truth.label

            session.mode.value = "normal"
            session._snapshot()
            browser.close()
        import cv2

        snaps = list((compare_dir / "gabor" / "renders").glob("snapshot-*-normal.png"))
        assert len(snaps) == 1 and cv2.imread(str(snaps[0])).shape == (480, 640, 3)
    finally:
        viewer.stop()


def test_viewer_needs_something_to_show():
    with pytest.raises(SplatzooError, match="nothing to view"):
        Viewer([])


def test_training_can_be_watched(tmp_path):
    """`train --viewer`: the viewer serves while training runs, receives copies of the parameters and the training
    cameras; training on several processes cannot be watched (a clear error before anything runs)."""
    import urllib.request

    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.viewer import TrainingWatch

    data = make_synthetic_scene("plain", tmp_path / "data", views=6, width=32, height=32)
    watch = TrainingWatch("live", port=0, backend="cpu")
    try:
        assert b"<html" in urllib.request.urlopen(watch.viewer.url, timeout=10).read().lower()
        train(data, "gabor", {}, TrainConfig(iterations=12, backend="cpu", num_primitives=200, densify=False),
              tmp_path / "run", progress=False, evaluate_at_end=False, watch=watch)
        assert watch.live.iteration == 12 and watch.live.version >= 2  # the first step and the last (forced)
        assert len(watch.source.views) == 5 and len(watch.viewer.frustums) == 5
        assert watch.source.model().num_primitives == 200
        with pytest.raises(SplatzooError, match="one process"):
            train(data, "gabor", {}, TrainConfig(iterations=2, nproc=2), tmp_path / "two", watch=watch)
        assert not (tmp_path / "two").exists()
    finally:
        watch.viewer.stop()


def test_only_the_viewers_own_pages_open_its_websocket(compare_dir):
    """A web page elsewhere (another Origin) or a re-resolved name (DNS rebinding) is refused at the handshake;
    the viewer's own page and scripts without an Origin connect."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    viewer = view([compare_dir / "gabor"], port=0, backend="cpu")
    try:
        url = f"ws://127.0.0.1:{viewer.port}"
        own = f"http://127.0.0.1:{viewer.port}"
        protocol = ["viser-v" + __import__("viser").__version__]
        rebound = f"ws://evil.example:{viewer.port}"  # a name that re-resolved to 127.0.0.1 (DNS rebinding)
        for target, origin in ((url, "https://evil.example"), (url, "null"),
                               (rebound, f"http://evil.example:{viewer.port}")):
            sock = socket.create_connection(("127.0.0.1", viewer.port), timeout=10)
            with pytest.raises(InvalidStatus) as e:
                connect(target, sock=sock, origin=origin, subprotocols=protocol, open_timeout=10)
            assert e.value.response.status_code == 403, (target, origin)
        for origin in (own, None):
            with connect(url, origin=origin, subprotocols=protocol, open_timeout=10) as ws:
                assert ws.subprotocol == protocol[0]
    finally:
        viewer.stop()


def test_handshake_rules():
    from splatzoo.viewer import handshake_refusal

    ok = {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:8080"}
    assert handshake_refusal(ok, "127.0.0.1") is None
    assert handshake_refusal({"Host": "localhost:8080", "Origin": "http://localhost:8080"}, "127.0.0.1") is None
    assert handshake_refusal({"Host": "[::1]:8080"}, "::1") is None
    assert "may not connect" in handshake_refusal({**ok, "Origin": "http://localhost:8080"}, "127.0.0.1")
    assert "not for the name" in handshake_refusal({"Host": "rebound.example:8080",
                                                    "Origin": "http://rebound.example:8080"}, "127.0.0.1")
    # served to the network (--host 0.0.0.0): any name, but still only its own pages
    assert handshake_refusal({"Host": "10.1.2.3:8080", "Origin": "http://10.1.2.3:8080"}, "0.0.0.0") is None
    assert handshake_refusal({"Host": "10.1.2.3:8080", "Origin": "http://evil.example"}, "0.0.0.0") is not None


def test_client_values_are_brought_into_bounds(compare_dir, tmp_path):
    """Every GUI value arrives from the client unchecked: the still size, the camera's size and field of view,
    a pose of NaNs, an unknown mode (which also names snapshot files) and a burst of snapshot presses."""
    import math
    from types import SimpleNamespace

    from splatzoo.viewer import FULL_SIZES, _Session

    session = object.__new__(_Session)
    c = SimpleNamespace(image_width=1 << 20, image_height=1 << 20, fov=math.radians(179.9), wxyz=(2.0, 0, 0, 0),
                        position=(0.0, 0.0, -1e6))
    session.client = SimpleNamespace(camera=c)
    cam = session.camera(8192)
    assert max(cam.width, cam.height) == FULL_SIZES[1]
    fov = 2 * math.degrees(math.atan(cam.height / 2 / float(cam.K[1, 1])))
    assert fov <= 170.0 + 1e-6
    assert torch.allclose(cam.R @ cam.R.T, torch.eye(3, dtype=cam.R.dtype), atol=1e-9)  # the quaternion normalised
    c.position = (float("nan"), 0.0, 0.0)
    assert session.camera(512) is None
    c.position, c.wxyz = (0.0, 0.0, -3.0), (0.0, 0.0, 0.0, 0.0)
    assert session.camera(512) is None

    session.mode = SimpleNamespace(value="../../../escape")
    assert session.render_mode() == "rgb"

    sent = []
    session.full = SimpleNamespace(value=256)
    session.viewer = SimpleNamespace(snapshot_dir=tmp_path / "snaps")
    c.wxyz = (1.0, 0.0, 0.0, 0.0)
    c.image_width, c.image_height = 32, 24
    session.render = lambda cam: np.zeros((cam.height, cam.width, 3), np.uint8)
    session.client.send_file_download = lambda name, data: sent.append(name)
    session.client.add_notification = lambda **kw: None
    for _ in range(5):
        session._snapshot()
    assert len(sent) == 1 and sent[0].endswith("-rgb.png")
    assert [p.name for p in (tmp_path / "snaps").iterdir()] == sent
