"""Cameras between nerfstudio's convention and splatzoo's, in plain torch (no nerfstudio import).

nerfstudio keeps camera-to-world [3,4] matrices with OpenGL axes (+x right, +y up, +z backward); splatzoo keeps
world-to-camera [4,4] matrices with OpenCV axes (+x right, +y down, +z forward). Both put pixel (i, j)'s centre at
(i + 0.5, j + 0.5) and use pinhole intrinsics in pixels, so only the y and z axes flip.
"""
from __future__ import annotations

import torch

from ...types import Camera

_FLIP = torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)  # OpenGL <-> OpenCV camera axes


def opengl_camera_to_world(camera: Camera) -> torch.Tensor:
    """nerfstudio's camera_to_worlds [3,4] (OpenGL axes, float32) of a splatzoo camera."""
    w2c = camera.world_to_camera.detach().double().cpu()
    R, t = w2c[:3, :3], w2c[:3, 3]
    c2w = torch.cat([R.T * _FLIP, (-R.T @ t)[:, None]], dim=1)  # columns: the camera axes, then its centre
    return c2w.float()


def splatzoo_camera(camera_to_world, fx, fy, cx, cy, width: int, height: int, name: str = "") -> Camera:
    """The splatzoo Camera (float32) of one nerfstudio camera: its camera_to_worlds [3,4] (OpenGL axes) and
    intrinsics in pixels."""
    c2w = torch.as_tensor(camera_to_world).detach().double().cpu().reshape(3, 4)
    R = (c2w[:, :3] * _FLIP).T  # world-to-camera rotation, OpenCV axes
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ c2w[:, 3]
    K = torch.tensor([[float(fx), 0.0, float(cx)], [0.0, float(fy), float(cy)], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(w2c, K, int(width), int(height), name).to(dtype=torch.float32)


def ray_distance(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Distance along each pixel's ray [H,W] from splatzoo's camera depth z [H,W]: nerfstudio's depth outputs
    (the viewer composites them as ray lengths)."""
    K = camera.K.to(depth)
    h, w = depth.shape
    x = (torch.arange(w, device=depth.device, dtype=depth.dtype) + 0.5 - K[0, 2]) / K[0, 0]
    y = (torch.arange(h, device=depth.device, dtype=depth.dtype) + 0.5 - K[1, 2]) / K[1, 1]
    return depth * torch.sqrt(1 + x[None, :] ** 2 + y[:, None] ** 2)
