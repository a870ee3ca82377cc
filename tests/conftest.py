import os
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch starts OpenMP; see splatzoo/__init__.py
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))  # the shared scene helpers in tests/scenes.py

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))

# Every backend, the test-only emulated CUDA kernels included. Parametrising by name builds nothing at collection:
# the fixtures below build (or skip, for a CUDA device that is not there) when a test runs.
ALL_BACKENDS = ("reference", "cpu", "cuda-emulated", "cuda")
NATIVE_BACKENDS = ("cpu", "cuda-emulated", "cuda")


def backend_for_test(name: str):
    """The registered backend `name`, ready to run: skipped only for want of a GPU; a build failure fails."""
    from splatzoo.rasterizers import BACKENDS

    b = BACKENDS.get(name)
    if b.device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    reason = b.unavailable_reason()
    if reason is not None:
        pytest.fail(f"the {name} rasterizer backend cannot run here: {reason}")
    return b


def pytest_addoption(parser):
    parser.addoption("--fuzz-cases", type=int, default=None, metavar="N",
                     help="mutated inputs per loader in tests/test_fuzz.py (default: a quick CI run); raise it after "
                          "changing a loader")


def pytest_generate_tests(metafunc):
    if "any_backend" in metafunc.fixturenames:
        metafunc.parametrize("any_backend", ALL_BACKENDS, indirect=True)
    if "native_backend" in metafunc.fixturenames:
        metafunc.parametrize("native_backend", NATIVE_BACKENDS, indirect=True)


@pytest.fixture
def any_backend(request):
    return backend_for_test(request.param)


@pytest.fixture
def native_backend(request):
    return backend_for_test(request.param)


@pytest.fixture(scope="module")
def trained_2dgs(tmp_path_factory):
    """A small 2dgs model trained on a synthetic scene, its test view and its run folder."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import load_run, train
    from splatzoo.training import TrainConfig

    root = tmp_path_factory.mktemp("trained_2dgs")
    data = make_synthetic_scene("sweater", root / "data", views=10, width=64, height=64, background=(1, 1, 1))
    train(data, "2dgs", {}, TrainConfig(iterations=300, backend="cpu", num_primitives=1000, densify=False),
          root / "2dgs", progress=False, evaluate_at_end=False)
    model, scene, _ = load_run(root / "2dgs", "cpu")
    return model, scene.test[0], root / "2dgs"


def install_plugin(tmp_path_factory, source: Path) -> dict:
    """Install the test plugin at `source` (tests/plugins/...) into a fresh folder, built from a copy so that no
    build artefacts land in the source tree; the environment whose PYTHONPATH finds it."""
    import subprocess

    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    subprocess.run(["cp", "-r", str(source), str(build)], check=True)
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-warn-script-location", "--target", str(target), str(build / source.name)],
                   check=True, capture_output=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(target) + os.pathsep + env.get("PYTHONPATH", "")
    return env
