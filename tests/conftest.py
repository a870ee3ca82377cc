import os
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch starts OpenMP; see splatzoo/__init__.py
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))  # the shared scene helpers in tests/scenes.py

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


def native_backends() -> list[str]:
    """Native backends usable here (building the extension once per session)."""
    from splatzoo.rasterizers import native

    names = []
    try:
        if native.cpu_available():
            names.append("cpu")
    except Exception:
        pass
    try:
        if native.cuda_available():
            names.append("cuda")
    except Exception:
        pass
    return names


def pytest_generate_tests(metafunc):
    if "any_backend" in metafunc.fixturenames:
        metafunc.parametrize("any_backend", ["reference"] + native_backends())
