"""resize, as torchvision.transforms.functional.resize does it for tensors (bilinear)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def _output_size(height: int, width: int, size, max_size: int | None) -> tuple[int, int]:
    if isinstance(size, int) or (isinstance(size, (list, tuple)) and len(size) == 1):
        short = int(size if isinstance(size, int) else size[0])
        if width <= height:
            new_w, new_h = short, int(short * height / width)
        else:
            new_w, new_h = int(short * width / height), short
        if max_size is not None and max(new_h, new_w) > max_size:
            scale = max_size / max(new_h, new_w)
            new_h, new_w = int(new_h * scale), int(new_w * scale)
        return new_h, new_w
    return int(size[0]), int(size[1])


def resize(img: torch.Tensor, size, interpolation=None, max_size: int | None = None, antialias=True) -> torch.Tensor:
    """img [..., C, H, W]; size: the smaller edge (an int, aspect kept) or (height, width). uint8 stays uint8."""
    if not isinstance(img, torch.Tensor):
        raise TypeError("this torchvision stand-in resizes tensors only")
    h, w = _output_size(img.shape[-2], img.shape[-1], size, max_size)
    lead = img.shape[:-3]
    x = img.reshape(-1, *img.shape[-3:]).float()
    out = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=bool(antialias))
    if img.dtype == torch.uint8:
        out = out.round().clamp(0, 255)
    return out.to(img.dtype).reshape(*lead, img.shape[-3], h, w)
