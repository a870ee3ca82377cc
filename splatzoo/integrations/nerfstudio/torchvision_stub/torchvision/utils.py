"""save_image and make_grid, as torchvision.utils has them, for float images in [0, 1]."""
from __future__ import annotations

import math

import numpy as np
import torch


def make_grid(tensor, nrow: int = 8, padding: int = 2, normalize: bool = False, value_range=None,
              scale_each: bool = False, pad_value: float = 0.0) -> torch.Tensor:
    """[B,C,H,W] (or a list of [C,H,W]) as one [C, rows x H, nrow x W] image; a single [C,H,W] is returned as is."""
    if isinstance(tensor, (list, tuple)):
        tensor = torch.stack(list(tensor))
    if tensor.dim() == 2:
        tensor = tensor[None]
    if tensor.dim() == 3:
        return tensor if tensor.shape[0] != 1 else tensor.expand(3, -1, -1)
    if normalize:
        lo, hi = value_range if value_range is not None else (float(tensor.min()), float(tensor.max()))
        tensor = (tensor - lo) / max(hi - lo, 1e-5)
    b, c, h, w = tensor.shape
    cols = min(nrow, b)
    rows = math.ceil(b / cols)
    grid = tensor.new_full((c, rows * (h + padding) + padding, cols * (w + padding) + padding), pad_value)
    for i in range(b):
        r, k = divmod(i, cols)
        grid[:, r * (h + padding) + padding:(r + 1) * (h + padding), k * (w + padding) + padding:
             (k + 1) * (w + padding)] = tensor[i]
    return grid


def save_image(tensor, fp, format=None, **kwargs) -> None:
    """Write [C,H,W] or [B,C,H,W] values in [0, 1] as an 8-bit image file (PIL)."""
    from PIL import Image

    grid = make_grid(tensor, **kwargs)
    array = (grid.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    Image.fromarray(np.ascontiguousarray(array.squeeze(2) if array.shape[2] == 1 else array)).save(fp, format=format)
