"""Render a splat PLY in third-party three.js splat viewers (Spark, GaussianSplats3D), and a glTF splat file
(KHR_gaussian_splatting) in the PlayCanvas engine, in headless Chromium.

A helper for tests and benchmarks, not a test file. tests/browser/ is a small npm project (pinned versions, a lock
file) with a static page that loads a PLY, sets the viewer's camera from a splatzoo `Camera` (intrinsics exactly,
off-centre principal point included), renders one frame once the splats are sorted and returns its pixels. Here a
local HTTP server on 127.0.0.1 serves that folder and the PLY, and Playwright drives Chromium with software WebGL.

    with BrowserViewers() as b:
        img = b.render("model.ply", camera, viewer="spark", background=(1, 1, 1))   # [H, W, 3] float in [0, 1]
        img = b.render_gltf("model.glb", camera)                                        # PlayCanvas
    img = render_in_viewer("model.ply", camera, viewer="gs3d")                     # one call, one browser

The glTF viewer has its own page (playcanvas.html, playcanvas.js), so the PLY viewers' page never loads the engine.
Needs Chromium (apt-get install -y chromium), Playwright (pip) and the viewers (npm ci --prefix tests/browser).
"""
from __future__ import annotations

import base64
import functools
import http.server
import io
import os
import shutil
import threading
import urllib.parse
from pathlib import Path

import numpy as np

from splatzoo.errors import SplatzooError

BROWSER_DIR = Path(__file__).resolve().parent / "browser"
VIEWERS = ("spark", "gs3d")
PACKAGES = ("three", "@sparkjsdev/spark", "@mkkellogg/gaussian-splats-3d")
GLTF_VIEWERS = ("playcanvas",)   # read glTF binaries with KHR_gaussian_splatting
GLTF_PACKAGES = ("playcanvas",)
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def find_chromium() -> str | None:
    """The Chromium executable to drive, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return "/usr/bin/chromium" if os.path.exists("/usr/bin/chromium") else None


def missing(packages: tuple[str, ...] = PACKAGES) -> str | None:
    """What is missing to render in the browser viewers of `packages` (PACKAGES: the PLY viewers; GLTF_PACKAGES:
    PlayCanvas) and how to install it, or None when all is there."""
    if find_chromium() is None:
        return "no Chromium found: install it (apt-get install -y chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright is not installed: pip install playwright"
    absent = [p for p in packages if not (BROWSER_DIR / "node_modules" / p / "package.json").exists()]
    if absent:
        return (f"the splat viewers are not installed ({', '.join(absent)} missing under tests/browser/node_modules): "
                "run npm ci --prefix tests/browser")
    return None


def camera_json(camera) -> dict:
    """A splatzoo Camera as the page takes it (OpenCV world_to_camera rows, pinhole intrinsics, image size)."""
    K = camera.K.detach().double().cpu()
    return {"world_to_camera": camera.world_to_camera.detach().double().cpu().tolist(),
            "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "width": int(camera.width), "height": int(camera.height)}


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves tests/browser/ at / and registered files at /files/<key>/<name>."""

    files: dict[str, Path] = {}

    def translate_path(self, path):
        parts = urllib.parse.urlparse(path).path.split("/")
        if len(parts) == 4 and parts[1] == "files" and parts[2] in self.files:
            registered, name = self.files[parts[2]], urllib.parse.unquote(parts[3])
            if name == registered.name:
                return str(registered)
            if name not in ("", ".", "..") and "/" not in name and "\\" not in name:
                return str(registered.parent / name)  # a file beside it (an OBJ's .mtl, a texture)
            return str(BROWSER_DIR / "no-such-file")  # a 404
        return super().translate_path(path)

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, *args):  # quiet: tests print their own numbers
        pass


class ViewerServer:
    """A local HTTP server on 127.0.0.1 (a free port) for the viewer page and the PLY files it loads."""

    def __init__(self):
        handler = type("Handler", (_Handler,), {"files": {}})
        self._files = handler.files
        self._httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                      functools.partial(handler, directory=str(BROWSER_DIR)))
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True)
        self._thread.start()
        self.url = f"http://127.0.0.1:{self._httpd.server_address[1]}"

    def add_file(self, path) -> str:
        """Serve `path`; returns its URL (ending in the file's own name, so viewers see the .ply extension)."""
        path = Path(path).resolve()
        key = str(len(self._files))
        self._files[key] = path
        return f"{self.url}/files/{key}/{urllib.parse.quote(path.name)}"

    def close(self):
        self._httpd.shutdown()
        self._httpd.server_close()


class BrowserViewers:
    """Headless Chromium with the viewer pages; `render` gives one frame of a PLY in a three.js viewer, `render_gltf`
    one of a glTF splat file in PlayCanvas. A context manager; `packages`: the viewers it needs (see `missing`)."""

    def __init__(self, timeout_s: float = 60.0, packages: tuple[str, ...] = PACKAGES):
        reason = missing(packages)
        if reason:
            raise SplatzooError(reason)
        self.timeout_ms = timeout_s * 1000
        self._server = self._pw = self._browser = None

    def __enter__(self):
        from playwright.sync_api import sync_playwright

        self._server = ViewerServer()
        try:
            self._pw = sync_playwright().start()
            self._browser = self._pw.chromium.launch(executable_path=find_chromium(), args=CHROMIUM_ARGS)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        if self._browser is not None:
            self._browser.close()
        if self._pw is not None:
            self._pw.stop()
        if self._server is not None:
            self._server.close()
        self._server = self._pw = self._browser = None

    def render(self, ply_path, camera, viewer: str = "spark", background=(1.0, 1.0, 1.0),
               options: dict | None = None) -> np.ndarray:
        """One frame of the PLY in `viewer` from splatzoo `camera` over `background` (rgb in [0, 1]), with the
        viewer's default settings unless `options` says otherwise (see tests/browser/render.js). Returns
        [H, W, 3] float64 in [0, 1] (8-bit values from the canvas)."""
        if viewer not in VIEWERS:
            raise SplatzooError(f"unknown viewer {viewer!r}; known: {', '.join(VIEWERS)}")
        if not Path(ply_path).is_file():
            raise SplatzooError(f"no PLY file at {ply_path}; write one with splatzoo.export.save_ply")
        args = {"url": self._server.add_file(ply_path), "viewer": viewer, "camera": camera_json(camera),
                "background": [float(c) for c in background], "options": options or {}}
        result = self._evaluate("window.splatReady", "window.renderSplat", args,
                                f"{viewer} failed to render {ply_path}",
                                viewport={"width": int(camera.width), "height": int(camera.height)})
        return self._image(result, camera, viewer)

    def render_gltf(self, glb_path, camera, viewer: str = "playcanvas", background=(1.0, 1.0, 1.0),
                    options: dict | None = None) -> np.ndarray:
        """One frame of the glTF binary `glb_path` (KHR_gaussian_splatting splats) in `viewer` (the PlayCanvas
        engine's own glb parser and splat renderer) from splatzoo `camera` over `background`, with the engine's
        default settings unless `options` (fields of its GSplatParams, see tests/browser/playcanvas.js) says
        otherwise. Returns [H, W, 3] float64 in [0, 1] (8-bit values from the canvas)."""
        if viewer not in GLTF_VIEWERS:
            raise SplatzooError(f"unknown glTF viewer {viewer!r}; known: {', '.join(GLTF_VIEWERS)}")
        if not Path(glb_path).is_file():
            raise SplatzooError(f"no glTF file at {glb_path}; write one with splatzoo.gltf_export.write_glb_splats")
        absent = missing(GLTF_PACKAGES)
        if absent:
            raise SplatzooError(absent)
        args = {"url": self._server.add_file(glb_path), "camera": camera_json(camera),
                "background": [float(c) for c in background], "options": options or {}}
        result = self._evaluate("window.gltfSplatReady", "window.renderGltfSplat", args,
                                f"{viewer} failed to render {glb_path}", page="playcanvas.html",
                                viewport={"width": int(camera.width), "height": int(camera.height)})
        return self._image(result, camera, viewer)

    @staticmethod
    def _image(result: dict, camera, viewer: str) -> np.ndarray:
        """The page's PNG data URL as [H, W, 3] float64 in [0, 1], checked against the camera's size."""
        from PIL import Image

        png = base64.b64decode(result["image"].split(",", 1)[1])
        img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255.0
        if img.shape != (camera.height, camera.width, 3):
            raise SplatzooError(f"{viewer} returned a {img.shape[1]}x{img.shape[0]} image for a "
                               f"{camera.width}x{camera.height} camera")
        return img

    def load_mesh(self, mesh_path) -> dict:
        """What three.js's own loaders read of a mesh file (.glb through GLTFLoader; .obj through OBJLoader with its
        .mtl beside it through MTLLoader): {meshes, vertices, triangles, uvs, textured, textureSize, meanTexel}."""
        mesh_path = Path(mesh_path)
        if not mesh_path.is_file():
            raise SplatzooError(f"no mesh file at {mesh_path}")
        url = self._server.add_file(mesh_path)
        mtl = mesh_path.with_suffix(".mtl")
        args = {"url": url, "mtl": url.rsplit("/", 1)[0] + "/" + urllib.parse.quote(mtl.name)
                if mesh_path.suffix.lower() == ".obj" and mtl.is_file() else None}
        return self._evaluate("window.meshReady", "window.loadMesh", args, f"three.js could not load {mesh_path}")

    def _evaluate(self, ready: str, function: str, args: dict, failure: str, viewport: dict | None = None,
                  page: str = "index.html"):
        """await function(args) on a fresh load of `page` of the viewer site, once `ready` is true; a failure (with
        the page's own errors) becomes a SplatzooError starting with `failure`."""
        tab = self._browser.new_page(**({"viewport": viewport} if viewport else {}))
        errors: list[str] = []
        tab.on("pageerror", lambda e: errors.append(str(e)))
        try:
            tab.set_default_timeout(self.timeout_ms)
            tab.goto(f"{self._server.url}/{page}")
            tab.wait_for_function(f"{ready} === true")
            try:
                return tab.evaluate(f"args => {function}(args)", args)
            except Exception as e:
                raise SplatzooError(f"{failure}: {e}"
                                   + (f" (page errors: {'; '.join(errors)})" if errors else "")) from None
        finally:
            tab.close()


def render_in_viewer(ply_path, camera, viewer: str = "spark", background=(1.0, 1.0, 1.0),
                     options: dict | None = None) -> np.ndarray:
    """One frame of the PLY in `viewer` ("spark" or "gs3d") from splatzoo `camera`: [H, W, 3] float in [0, 1].
    Starts and stops a browser; for several renders use BrowserViewers."""
    with BrowserViewers() as b:
        return b.render(ply_path, camera, viewer=viewer, background=background, options=options)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-12))
