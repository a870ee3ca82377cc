"""`splatzoo view`: a live viewer in the browser, built on viser, rendering on the server with splatzoo's rasterizer.

The browser sends its camera; the server renders the model for that camera and sends the image back as the page's
background. While the camera moves, frames are rendered small (fast enough on a 2-core CPU); once it has been still
for a moment, one frame at the page's full size follows. The rendering half (cameras, render modes, side-by-side
layout) is plain functions of a model and a camera, so it is tested without a browser.

Render modes: rgb, depth, normal, alpha, surfels (each surfel one random colour), waves (how many waves each
surfel keeps, as a heat map) and frequency (each surfel's highest wave frequency on screen against the pixel's
Nyquist limit of 0.5 cycles per pixel: 1 in the middle of the colour map; above it the wave aliases).
"""
from __future__ import annotations

import ipaddress
import math
import socket
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .display import random_colors, recolored
from .errors import SplatzooError
from .types import Camera, Surfels

MODES = ("rgb", "depth", "normal", "alpha", "surfels", "waves", "frequency")
LAYOUTS = ("toggle", "side by side")
SETTLE_SECONDS = 0.25  # still this long after a move: render at full size
# The GUI's bounds, enforced on the server too: a client can send any value for any control
MOVING_SIZES = (64, 1024)   # px, longest side while the camera moves
FULL_SIZES = (128, 4096)    # px, longest side once it is still (and of snapshots)
FOV_DEGREES = (1.0, 170.0)  # the browser camera's vertical field of view
SNAPSHOT_SECONDS = 2.0      # at most one snapshot per browser in this time


# --- cameras ------------------------------------------------------------------------------------------------------

def _quat_wxyz_to_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method: the largest diagonal term first)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2 * math.sqrt(1 + t)
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2 * math.sqrt(1 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] >= R[2, 2]:
        s = 2 * math.sqrt(1 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2 * math.sqrt(1 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4]
    q = np.array(q)
    return q if q[0] >= 0 else -q


def browser_camera(wxyz, position, fov: float, width: int, height: int) -> Camera:
    """The splatzoo camera of a viser camera: `wxyz` and `position` place the camera in the world (OpenCV axes:
    +z forward, +y down, as splatzoo's), `fov` is the vertical field of view in radians, pixels are square."""
    c2w_rotation = _quat_wxyz_to_matrix(wxyz)
    w2c = np.eye(4)
    w2c[:3, :3] = c2w_rotation.T
    w2c[:3, 3] = -c2w_rotation.T @ np.asarray(position, dtype=np.float64)
    f = 0.5 * height / math.tan(0.5 * fov)
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.from_numpy(w2c), torch.from_numpy(K), width, height)


def camera_pose(cam: Camera) -> dict:
    """A splatzoo camera as viser places it: wxyz, position, vertical fov (radians) and aspect."""
    c2w = cam.camera_to_world.double().cpu().numpy()
    fy = float(cam.K[1, 1])
    return {"wxyz": _matrix_to_quat_wxyz(c2w[:3, :3]), "position": c2w[:3, 3],
            "fov": 2 * math.atan(0.5 * cam.height / fy), "aspect": cam.width / cam.height}


def focus_point(cams: list[Camera]) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares): what a capture looks at, the centre to
    orbit about."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cams:
        c2w = cam.camera_to_world.double().cpu().numpy()
        d, c = c2w[:3, 2], c2w[:3, 3]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:  # all axes parallel: a point ahead of the cameras
        c2w = cams[0].camera_to_world.double().cpu().numpy()
        return c2w[:3, 3] + c2w[:3, 2]


def fit_size(width: int, height: int, longest: int) -> tuple[int, int]:
    """(width, height) scaled down so that the longer side is at most `longest` (never up)."""
    s = min(1.0, longest / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


# --- rendering ----------------------------------------------------------------------------------------------------

def _colormap(values: torch.Tensor, name: str = "turbo") -> torch.Tensor:
    """[...] in [0,1] -> [..., 3] colours in [0,1] (OpenCV's colour maps)."""
    import cv2

    table = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None],
                              {"turbo": cv2.COLORMAP_TURBO, "inferno": cv2.COLORMAP_INFERNO}[name])[:, 0, ::-1]
    table = torch.from_numpy(table.copy()).to(values.device, torch.float32) / 255
    return table[(values.clamp(0, 1) * 255).round().long()]


def surfel_wave_counts(surfels: Surfels) -> torch.Tensor:
    """[N] waves each surfel uses (adaptive models keep fewer; a wave of zero amplitude counts as none)."""
    return surfel_wave_mask(surfels).sum(1).float()


def surfel_cycles_per_pixel(surfels: Surfels, cam: Camera) -> torch.Tensor:
    """[N] the highest frequency among each surfel's waves on screen, in cycles per pixel, at the surfel's centre
    and facing the camera (a tilted surfel only squeezes its waves further). A wave vector k is in radians per
    sigma along (u, v): in the world it is (k_u / s_u, k_v / s_v) radians per unit, and a pixel at depth z spans
    z / f units."""
    n = surfels.num
    if surfels.num_waves == 0:
        return torch.zeros(n, device=surfels.means.device)
    k_world = surfels.wave_vectors / surfels.scales[:, None, :].clamp_min(1e-12)
    per_wave = k_world.norm(dim=-1)  # [N,K] radians per world unit
    per_wave = torch.where(surfel_wave_mask(surfels), per_wave, torch.zeros_like(per_wave))
    R, t = cam.R.to(surfels.means), cam.t.to(surfels.means)
    depth = (surfels.means @ R.T + t)[:, 2].clamp_min(1e-9)
    f = float(cam.K[0, 0] + cam.K[1, 1]) / 2
    return per_wave.amax(1) * depth / f / (2 * math.pi)


def surfel_wave_mask(surfels: Surfels) -> torch.Tensor:
    """[N,K] which waves each surfel uses."""
    used = surfels.wave_amplitudes.abs().amax(-1) > 0
    if surfels.wave_counts is not None:
        used &= torch.arange(surfels.num_waves, device=used.device)[None] < surfels.wave_counts[:, None]
    return used


def render_frame(model, cam: Camera, mode: str = "rgb", *, background=(0.0, 0.0, 0.0), backend: str = "auto",
                 max_waves: int | None = None) -> np.ndarray:
    """One viewer frame: uint8 [H,W,3] of `model` seen from `cam` in render `mode` (see MODES)."""
    if mode not in MODES:
        raise SplatzooError(f"unknown render mode {mode!r}; choose one of {', '.join(MODES)}")
    device = next(model.parameters()).device
    cam = cam.to(device, torch.float32)
    with torch.no_grad():
        surfels = model.surfels(cam)
        bg = background
        if mode == "surfels":
            surfels = recolored(surfels, random_colors(surfels.num))
            bg = (0.0, 0.0, 0.0)
        elif mode == "waves":
            k = max_waves or max(surfels.num_waves, 1)
            surfels = recolored(surfels, _colormap(surfel_wave_counts(surfels) / k, "inferno"))
            bg = (0.0, 0.0, 0.0)
        elif mode == "frequency":  # 0.5 cycles per pixel (Nyquist) in the middle of the map
            surfels = recolored(surfels, _colormap(surfel_cycles_per_pixel(surfels, cam)))
            bg = (0.0, 0.0, 0.0)
        # colour and alpha only where that is all the mode shows (no depth, normal or distortion to compute)
        image_only = mode in ("rgb", "surfels", "waves", "frequency", "alpha")
        out = model.render(cam, background=bg, backend=backend, surfels=surfels, image_only=image_only)
        if mode in ("rgb", "surfels", "waves", "frequency"):
            image = out.rgb
        elif mode == "alpha":
            image = out.alpha[..., None].expand(-1, -1, 3)
        elif mode == "normal":
            image = torch.where(out.alpha[..., None] > 1e-3, out.normal * 0.5 + 0.5, torch.zeros_like(out.normal))
        else:  # depth: the surface's camera depth, near to far over the visible range
            hit = out.alpha > 0.5
            d = out.depth
            if hit.any():
                lo, hi = torch.quantile(d[hit].float(), torch.tensor([0.01, 0.99], device=d.device))
                image = _colormap((d - lo) / (hi - lo).clamp_min(1e-9)) * hit[..., None]
            else:
                image = torch.zeros(*d.shape, 3, device=d.device)
    return (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def render_layout(models: list, cam: Camera, mode: str, backgrounds: list, *, backend: str = "auto",
                  max_waves: int | None = None, gap: int = 2) -> np.ndarray:
    """Several models side by side in one image of `cam`'s size, sharing its viewpoint and vertical field of view:
    each gets an equal slice of the width."""
    n = len(models)
    if n == 1:
        return render_frame(models[0], cam, mode, background=backgrounds[0], backend=backend, max_waves=max_waves)
    width = max(1, (cam.width - gap * (n - 1)) // n)
    K = cam.K.clone()
    K[0, 2] = width / 2
    part = Camera(cam.world_to_camera, K, width, cam.height)
    image = np.full((cam.height, cam.width, 3), 255, np.uint8)
    for i, (model, bg) in enumerate(zip(models, backgrounds)):
        x = i * (width + gap)
        image[:, x:x + width] = render_frame(model, part, mode, background=bg, backend=backend, max_waves=max_waves)
    return image


# --- what is shown ------------------------------------------------------------------------------------------------

class LiveModel:
    """The model of a training in progress, as the viewer sees it: the training loop publishes a copy of the
    parameters at most every `every` seconds (a copy, so that training never waits for a render and a render never
    sees a half-updated model); the viewer renders the latest copy."""

    def __init__(self, every: float = 0.5):
        self.every = every
        self._lock = threading.Lock()
        self._checkpoint, self._model, self._published = None, None, -math.inf
        self.version = 0
        self.iteration = 0

    def publish(self, net, iteration: int = 0, *, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._published < self.every:
            return
        ckpt = net.checkpoint()
        ckpt["state"] = {k: v.clone() for k, v in ckpt["state"].items()}
        with self._lock:
            self._checkpoint, self._model = ckpt, None
            self.version += 1
            self.iteration = iteration
        self._published = now

    def model(self):
        from .zoo import model_from_checkpoint

        with self._lock:
            if self._model is None and self._checkpoint is not None:
                self._model = model_from_checkpoint(self._checkpoint)
            return self._model


@dataclass
class Source:
    """One model in the viewer: a run's trained model (or the model of a training in progress), its training views
    (cameras and ground truth) and its background colour."""

    label: str
    views: list = field(default_factory=list)
    background: tuple = (0.0, 0.0, 0.0)
    fixed_model: object = None
    live: LiveModel | None = None
    note: str = ""

    def model(self):
        return self.live.model() if self.live is not None else self.fixed_model

    @property
    def version(self) -> int:
        return self.live.version if self.live is not None else 0


def _is_run_folder(path: Path) -> bool:
    return (path / "config.json").exists() or (path / "model.pt").exists() or (path / "checkpoint.pt").exists()


def expand_runs(paths) -> list[Path]:
    """Run folders named on the command line; a folder that holds run folders (`splatzoo compare`'s output, whose
    runs are in its runs/ folder) stands for all of them, in name order."""
    from .integrations.nerfstudio import is_nerfstudio_output

    runs = []
    for p in map(Path, paths):
        if not p.exists():
            raise SplatzooError(f"{p} does not exist; name a run folder written by `splatzoo train` (or a folder "
                                "of runs, such as runs/compare)")
        if p.is_file() and p.suffix.lower() in (".ply", ".pt", ".spz", ".sog", ".splat", ".ksplat"):
            # a model file (other splat formats through splat-transform): viewed without training cameras
            runs.append(p)
            continue
        if not p.is_dir():
            raise SplatzooError(f"{p} is not a folder; name a run folder written by `splatzoo train` or a model file "
                                "(.ply or .pt)")
        if _is_run_folder(p) or is_nerfstudio_output(p):  # an ns-train output: its model, without cameras
            runs.append(p)
            continue
        inner = sorted(q for q in p.iterdir() if q.is_dir() and _is_run_folder(q))
        if not inner and (p / "runs").is_dir():  # `splatzoo compare` and `sweep` keep their runs in OUT/runs/
            inner = sorted(q for q in (p / "runs").iterdir() if q.is_dir() and _is_run_folder(q))
        if not inner:
            raise SplatzooError(f"{p} is neither a run folder (config.json, model.pt) nor a folder of runs")
        runs.extend(inner)
    return runs


def viewer_source(opened) -> Source:
    """A model from splatzoo.model_files.open_model (a viewer opens with latest=True, so an interrupted run shows its
    last checkpoint) as a viewer source: the model and, for a run folder, its training views when the dataset is still
    where it was."""
    from .runs import Run

    model, path = opened.model, opened.path
    if opened.format != "run":  # a model file (.ply from `splatzoo export` or another tool, .pt): no cameras
        return Source(label=f"{Path(path).name} ({model.name})", fixed_model=model,
                      note="a model file: no training cameras (view its run, or orbit from the default view)")
    run = Run(path)
    note = opened.note
    views, background = [], (0.0, 0.0, 0.0)
    try:
        scene = run.scene()
        views, background = list(scene.train), tuple(scene.background)
    except SplatzooError as e:  # the model can still be viewed; the cameras cannot
        note = (note + "; " if note else "") + f"no training cameras ({e})"
        bg = run.record().get("scene_options", {}).get("background") if run.config_path.exists() else None
        background = tuple(bg) if bg else background
    label = path.name if path.name not in ("", ".") else str(path.resolve().name)
    return Source(label=f"{label} ({model.name})", views=views, background=background, fixed_model=model, note=note)


# --- the server ---------------------------------------------------------------------------------------------------

def check_address(host: str, port: int) -> None:
    """A clear error when `port` on `host` cannot be served (in use, or an address this machine does not have)."""
    if not 0 <= port <= 65535:
        raise SplatzooError(f"--port must be between 1 and 65535, got {port}")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            if port and e.errno in (98, 48):  # EADDRINUSE (Linux, macOS)
                raise SplatzooError(f"port {port} on {host} is in use (another viewer?); pass --port with a free "
                                    "port") from None
            raise SplatzooError(f"cannot serve on {host}:{port}: {e.strerror or e}") from None


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# ---- who may open the viewer's websocket ----------------------------------------------------------------------
# A browser lets any web page open a websocket to 127.0.0.1, and viser accepts every handshake that names its
# protocol: a page the user visits elsewhere could watch the models and drive the viewer. So the handshake must come
# from a page of the viewer itself (its Origin is the Host it asks for), and, on a loopback viewer, ask for a
# loopback name (a page whose domain re-resolves to 127.0.0.1, DNS rebinding, would otherwise pass as same-origin).
_GUARDED_HOSTS: set[str] = set()


def handshake_refusal(headers, served_host: str) -> str | None:
    """Why a websocket handshake with these request headers is refused by a viewer serving on `served_host`; None
    when it is accepted. Clients that send no Origin (scripts, not web pages) are accepted."""
    from urllib.parse import urlsplit

    try:
        asked, origin = headers.get("Host", ""), headers.get("Origin")
    except Exception:  # a header given twice (websockets raises MultipleValuesError)
        return "a Host or Origin header given more than once"
    try:
        name = urlsplit("//" + asked).hostname or ""
    except ValueError:
        return f"a malformed Host header {asked[:80]!r}"
    if is_loopback(served_host) and not is_loopback(name):
        return f"this viewer serves on {served_host} only, not for the name {asked!r}"
    if origin is not None and urlsplit(origin).netloc.lower() != asked.lower():
        return f"a page from {origin} may not connect to this viewer (open http://{asked}/ itself)"
    return None


def _guard_websockets(host: str) -> None:
    """Have every websocket server started on `host` (viser's) check handshake_refusal first: websockets' serve is
    wrapped once per process, and applies the check only to the hosts viewers serve on."""
    from http import HTTPStatus

    import websockets.asyncio.server as ws_server

    _GUARDED_HOSTS.add(host)
    if getattr(ws_server.serve, "splatzoo_guard", False):
        return
    original = ws_server.serve

    def serve(handler, host=None, port=None, *args, process_request=None, **kwargs):
        if host in _GUARDED_HOSTS:
            inner, served = process_request, host

            def process_request(connection, request):
                if request.headers.get("Upgrade", "").lower() == "websocket":
                    why = handshake_refusal(request.headers, served)
                    if why is not None:
                        return connection.respond(HTTPStatus.FORBIDDEN, f"splatzoo viewer: {why}\n")
                return inner(connection, request) if inner is not None else None
        return original(handler, host, port, *args, process_request=process_request, **kwargs)

    serve.splatzoo_guard = True
    ws_server.serve = serve


class Viewer:
    """A viser server showing `sources` (one or several models, sharing each browser's camera).

    start() returns once the server listens; stop() ends it. Rendering happens on one worker thread per browser,
    one frame at a time across browsers (two cores do not render two frames faster than one)."""

    def __init__(self, sources: list[Source], *, host: str = "127.0.0.1", port: int = 8080, backend: str = "auto",
                 moving_size: int = 256, full_size: int = 1920, snapshot_dir: Path | None = None, title="splatzoo"):
        if not sources:
            raise SplatzooError("nothing to view: name at least one run folder")
        self.sources = sources
        self.host, self.port, self.backend = host, port, backend
        self.moving_size, self.full_size = moving_size, full_size
        self.snapshot_dir = snapshot_dir
        self.title = title
        self.server = None
        self.sessions: dict[int, _Session] = {}
        self.render_lock = threading.Lock()
        self.stopped = threading.Event()
        self.focus = np.zeros(3)
        self.frustums = []

    # what every browser sees first: the first training camera of the first source that has one; with none (model
    # files), a camera that frames the first model's surfels
    def home_camera(self) -> Camera | None:
        for s in self.sources:
            if s.views:
                return s.views[0].camera
        model = self.sources[0].model() if self.sources else None
        means = getattr(model, "means", None)
        if not isinstance(means, torch.Tensor) or means.ndim != 2 or not len(means):
            return None
        pts = means.detach().double().cpu()
        center = pts.median(0).values
        radius = float(torch.quantile((pts - center).norm(dim=1), 0.9)) or 1.0
        return Camera.look_at(center + torch.tensor([0.0, -0.6, -1.0], dtype=torch.float64) * 2.2 * radius, center,
                              fov_deg=50.0, width=640, height=480)

    def show_cameras(self, visible: bool) -> None:
        for handle in self.frustums:
            handle.visible = visible

    def start(self) -> "Viewer":
        try:
            import viser
        except ImportError:
            raise SplatzooError("the viewer needs viser: pip install 'splatzoo[viewer]'") from None

        check_address(self.host, self.port)
        _guard_websockets(self.host)
        self.server = viser.ViserServer(host=self.host, port=self.port, label=self.title, verbose=False)
        actual = self.server.get_port()
        if self.port and actual != self.port:  # taken between the check and the bind
            self.server.stop()
            raise SplatzooError(f"port {self.port} on {self.host} is in use; pass --port with a free port")
        self.port = actual
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        # a frame rendered as a browser leaves has nowhere to go: nothing to warn about
        warnings.filterwarnings("ignore", message="Queued a .* on a closed connection")
        for source in self.sources:
            self.add_views(source, source.views)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        return self

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def stop(self) -> None:
        self.stopped.set()
        for s in list(self.sessions.values()):
            s.wake.set()
        if self.server is not None:
            self.server.stop()
            self.server = None

    def serve_forever(self) -> None:
        try:
            while not self.stopped.wait(0.5):
                pass
        finally:
            self.stop()

    def add_views(self, source: Source, views: list) -> None:
        """Show `source`'s training cameras (also after start: a training in progress hands them over once its
        scene is loaded); browsers that have no view yet go to the first one."""
        from .data.scene import camera_extent

        first = not any(s.views for s in self.sources)
        source.views = list(views)
        if not source.views or self.server is None:
            return
        si = self.sources.index(source)
        cams = [v.camera for v in source.views]
        if first:  # the world's up (the mean of the cameras' up, -y, directions) and the point to orbit about
            up = -np.mean([c.camera_to_world[:3, 1].double().numpy() for c in cams], axis=0)
            if np.linalg.norm(up) > 1e-6:
                self.server.scene.set_up_direction(tuple(up / np.linalg.norm(up)))
            self.focus = focus_point(cams)
        drawn = [s for s in self.sources[:si] if s.views]
        if drawn and len(drawn[0].views) == len(source.views):
            return  # runs of one comparison share their cameras: draw them once
        scale = 0.04 * camera_extent(cams)
        for i, view in enumerate(source.views):
            pose = camera_pose(view.camera)
            handle = self.server.scene.add_camera_frustum(
                f"/cameras/{si}/{i}", fov=pose["fov"], aspect=pose["aspect"], scale=scale, wxyz=pose["wxyz"],
                position=pose["position"], color=(60, 110, 220), thickness=1.5, thickness_units="screen")
            self.frustums.append(handle)
            handle.on_click(lambda event, si=si, i=i: self._jump(event.client, si, i))
        if first:
            for session in list(self.sessions.values()):
                session.go_home()

    def _jump(self, client, source_index: int, view_index: int) -> None:
        session = self.sessions.get(client.client_id)
        if session is not None:
            session.jump_to(self.sources[source_index].views[view_index])

    def _connect(self, client) -> None:
        session = _Session(self, client)
        self.sessions[client.client_id] = session
        session.start()

    def _disconnect(self, client) -> None:
        session = self.sessions.pop(client.client_id, None)
        if session is not None:
            session.close()


class _Session:
    """One browser: its controls, its camera and its render loop."""

    def __init__(self, viewer: Viewer, client):
        self.viewer, self.client = viewer, client
        self.wake = threading.Event()
        self.moved_at = time.monotonic()
        self.full_key = None  # what the last full-size frame showed (camera, settings, model versions)
        self.moving_key = None  # and the last small one
        self.closed = False
        self.frames = {"moving": 0, "full": 0}
        self.last_full = None  # (camera, image) of the last full-size frame sent: tests compare it
        self.full_sent = threading.Event()
        self._build_gui()
        self.thread = threading.Thread(target=self._loop, name=f"splatzoo-view-{client.client_id}", daemon=True)

    def _build_gui(self) -> None:
        gui, v = self.client.gui, self.viewer
        labels = [s.label for s in v.sources]
        self.mode = gui.add_dropdown("render", MODES, initial_value="rgb")
        self.shown = gui.add_dropdown("model", labels, initial_value=labels[0], visible=len(labels) > 1)
        self.layout = gui.add_dropdown("layout", LAYOUTS, initial_value="toggle", visible=len(labels) > 1)
        self.moving = gui.add_slider("moving size (px)", min=MOVING_SIZES[0], max=MOVING_SIZES[1], step=32,
                                     initial_value=v.moving_size)
        self.full = gui.add_slider("still size (px)", min=FULL_SIZES[0], max=FULL_SIZES[1], step=64,
                                   initial_value=v.full_size)
        self.cameras = gui.add_checkbox("training cameras (click one)", initial_value=True)
        self.cameras.on_update(lambda _: v.show_cameras(self.cameras.value))
        self.snapshot = gui.add_button("snapshot (PNG)")
        self.status = gui.add_markdown(self._status_text(None))
        self.truth = None
        for handle in (self.mode, self.shown, self.layout, self.moving, self.full):
            handle.on_update(lambda _: self._changed())
        self.snapshot.on_click(lambda _: self._snapshot())
        self.client.camera.on_update(lambda _: self._changed())

    def _status_text(self, seconds: float | None) -> str:
        lines = []
        for s in self.viewer.sources:
            model = s.model()
            what = f"{model.num_primitives:,} surfels" if model is not None else "waiting for the first parameters"
            live = f", training: iteration {s.live.iteration}" if s.live is not None else ""
            lines.append(f"**{s.label}**: {what}{live}" + (f" ({s.note})" if s.note else ""))
        if getattr(self, "layout", None) is not None and self.layout.value == "side by side":
            lines.append("side by side, left to right: " + " | ".join(s.label for s in self.viewer.sources))
        if getattr(self, "mode", None) is not None and self.mode.value == "frequency":
            lines.append("frequency: blue low, green at the pixel Nyquist limit (0.5 cycles/px), red above")
        if seconds is not None:
            lines.append(f"last frame {1000 * seconds:.0f} ms")
        return "  \n".join(lines)

    def start(self) -> None:
        self.go_home()
        self.thread.start()

    def go_home(self) -> None:
        home = self.viewer.home_camera()
        if home is not None:
            self._place(home)

    def close(self) -> None:
        self.closed = True
        self.wake.set()

    def _place(self, cam: Camera) -> None:
        pose = camera_pose(cam)
        c2w = cam.camera_to_world.double().numpy()
        with self.client.atomic():
            self.client.camera.fov = pose["fov"]
            self.client.camera.wxyz = pose["wxyz"]
            self.client.camera.position = pose["position"]
            # orbit about the point of the optical axis nearest to what the capture looks at
            ahead = max(float(np.dot(self.viewer.focus - pose["position"], c2w[:3, 2])), 1e-3)
            self.client.camera.look_at = pose["position"] + c2w[:3, 2] * ahead

    def jump_to(self, view) -> None:
        self._place(view.camera)
        truth = view.image_float().numpy()
        if self.truth is None:
            self.truth = self.client.gui.add_image(truth, label=f"ground truth: {view.name}", format="jpeg")
        else:
            self.truth.image, self.truth.label = truth, f"ground truth: {view.name}"

    def _changed(self) -> None:
        self.moved_at = time.monotonic()
        self.wake.set()

    # -- rendering ---------------------------------------------------------------------------------------------
    def camera(self, longest: int) -> Camera | None:
        """The browser's camera at `longest` px on its longer side, every client value brought into bounds (None
        for a camera no render can be made of: no size, a non-finite pose)."""
        c = self.client.camera
        try:
            width, height = int(c.image_width or 0), int(c.image_height or 0)
            fov = float(c.fov)
            wxyz, position = np.asarray(c.wxyz, dtype=np.float64), np.asarray(c.position, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            return None
        if width < 1 or height < 1 or not (np.isfinite(fov) and np.isfinite(wxyz).all() and np.isfinite(position).all()
                                           and np.linalg.norm(wxyz) > 1e-6 and wxyz.shape == (4,)
                                           and position.shape == (3,)):
            return None
        longest = int(min(max(longest, MOVING_SIZES[0]), FULL_SIZES[1]))
        fov = min(max(fov, math.radians(FOV_DEGREES[0])), math.radians(FOV_DEGREES[1]))
        width, height = fit_size(width, height, longest)
        return browser_camera(wxyz / np.linalg.norm(wxyz), position, fov, width, height)

    def render_mode(self) -> str:
        """The dropdown's mode, or rgb for a value the client made up (it also names snapshot files)."""
        return self.mode.value if self.mode.value in MODES else "rgb"

    def _shown(self) -> list[Source]:
        sources = self.viewer.sources
        if self.layout.value == "side by side":
            return sources
        return [next((s for s in sources if s.label == self.shown.value), sources[0])]

    def render(self, cam: Camera) -> np.ndarray | None:
        shown = self._shown()
        models = [s.model() for s in shown]
        if any(m is None for m in models):
            return None
        max_waves = max((getattr(m.config, "n_waves", 0) for m in models), default=0) or None
        with self.viewer.render_lock:
            return render_layout(models, cam, self.render_mode(), [s.background for s in shown],
                                 backend=self.viewer.backend, max_waves=max_waves)

    def _loop(self) -> None:
        while not (self.closed or self.viewer.stopped.is_set()):
            moving = time.monotonic() - self.moved_at < SETTLE_SECONDS
            cam = self.camera(int(self.moving.value if moving else self.full.value))
            if cam is None:
                self.wake.wait(0.05)
                self.wake.clear()
                continue
            key = (cam.world_to_camera.numpy().tobytes(), cam.K.numpy().tobytes(), self.render_mode(),
                   self.layout.value, self.shown.value, tuple(s.version for s in self._shown()))
            if key == (self.moving_key if moving else self.full_key):  # on screen already: wait for a change
                self.wake.wait(SETTLE_SECONDS / 5 if moving else 0.5 if any(s.live for s in self.viewer.sources)
                               else 5.0)
                self.wake.clear()
                continue
            try:
                started = time.perf_counter()
                image = self.render(cam)
                if image is None:  # a training that has not published its first parameters yet
                    self.wake.wait(0.2)
                    self.wake.clear()
                    continue
                self.client.scene.set_background_image(image, format="jpeg", jpeg_quality=80 if moving else 92)
                seconds = time.perf_counter() - started
            except Exception as e:  # a broken frame must not end the session; say what happened
                if self.closed or self.viewer.stopped.is_set():
                    return
                self.status.content = f"render failed: {e}"
                self.wake.wait(1.0)
                continue
            self.frames["moving" if moving else "full"] += 1
            if moving:
                self.moving_key = key
            else:
                self.full_key = key
                self.last_full = (cam, image)
                self.full_sent.set()
                self.status.content = self._status_text(seconds)

    def _snapshot(self) -> None:
        import cv2

        from .io import atomic_path

        now = time.monotonic()
        if now - getattr(self, "_last_snapshot", -math.inf) < SNAPSHOT_SECONDS:
            return  # a burst of presses (or a client's loop) makes one file, not many
        self._last_snapshot = now
        cam = self.camera(int(self.full.value))
        if cam is None:
            return
        image = self.render(cam)
        if image is None:
            return
        ok, png = cv2.imencode(".png", image[..., ::-1])
        name = f"snapshot-{time.strftime('%Y%m%d-%H%M%S')}-{self.render_mode()}.png"  # a known word: a safe name
        where = ""
        if self.viewer.snapshot_dir is not None:
            folder = Path(self.viewer.snapshot_dir)
            folder.mkdir(parents=True, exist_ok=True)
            with atomic_path(folder / name) as tmp:
                Path(tmp).write_bytes(png.tobytes())
            where = f" and saved as {folder / name}"
        self.client.send_file_download(name, png.tobytes())
        self.client.add_notification(title="snapshot", body=f"{name} downloaded{where}", auto_close_seconds=5.0)


class TrainingWatch:
    """`splatzoo train --viewer`: a viewer of the model in training. runs.train calls it after every step (it copies
    the parameters at most twice a second; training never waits for a render)."""

    def __init__(self, label: str, *, host: str = "127.0.0.1", port: int = 8080, backend: str = "auto",
                 snapshot_dir: Path | None = None):
        self.live = LiveModel()
        self.source = Source(label=label, live=self.live)
        _warn_if_open(host, port)
        self.viewer = Viewer([self.source], host=host, port=port, backend=backend, snapshot_dir=snapshot_dir,
                             title=f"splatzoo: training {label}").start()

    def __call__(self, net, iteration: int, scene, final: bool = False) -> None:
        if not self.source.views and scene.train:
            self.source.background = tuple(scene.background)
            self.viewer.add_views(self.source, scene.train)
        self.live.publish(net, iteration, force=final)


def _warn_if_open(host: str, port: int) -> None:
    if not is_loopback(host):
        print(f"warning: the viewer listens on {host}: anyone who can reach this machine on port {port} can see "
              "these models", file=sys.stderr)


def view(paths, *, host: str = "127.0.0.1", port: int = 8080, backend: str = "auto") -> Viewer:
    """Load the runs in `paths` and start a viewer for them (returns it started; `serve_forever()` blocks)."""
    from .model_files import open_model

    runs = expand_runs(paths)
    # every model is opened before a server starts: anything missing or damaged is an error here
    sources = [viewer_source(open_model(p, backend=backend, latest=True)) for p in runs]
    _warn_if_open(host, port)
    first = runs[0]
    snapshots = first.parent / f"{first.stem}_renders" if first.is_file() else first / "renders"
    return Viewer(sources, host=host, port=port, backend=backend, snapshot_dir=snapshots).start()
