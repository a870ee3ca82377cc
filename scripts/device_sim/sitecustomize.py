"""The GPU machine's missing packages, simulated on a CPU machine for `scripts/gpu-check.sh --dry-run`.

On PYTHONPATH (the dry run puts it there), this makes every package named in $GPU_SIM_HIDE (comma-separated
top-level names) unimportable and its distribution invisible to importlib.metadata, as on the device, where
KINDS.md's package list lacks them; a package that the check carries (a wheel installed into the --target folder,
or a folder such as .gpu-data/site) is still found when it lies under one of the paths in $GPU_SIM_ALLOW. So a dry
run that passes proves that the check needs nothing the device lacks beyond what it carries.
"""
import importlib.abc
import importlib.machinery
import importlib.metadata
import os
import sys

_HIDE = {n.strip() for n in os.environ.get("GPU_SIM_HIDE", "").split(",") if n.strip()}
_ALLOW = [os.path.realpath(p) for p in os.environ.get("GPU_SIM_ALLOW", "").split(os.pathsep) if p]


def _allowed(path: str) -> bool:
    real = os.path.realpath(path)
    return any(real == a or real.startswith(a + os.sep) for a in _ALLOW)


class _DeviceOnlyFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        top = fullname.partition(".")[0]
        if top not in _HIDE or fullname != top:
            return None  # submodules follow their package
        for entry in _ALLOW:  # a carried copy wins, and is the only one found
            spec = importlib.machinery.PathFinder.find_spec(fullname, [entry])
            if spec is not None:
                return spec
        raise ModuleNotFoundError(f"No module named {fullname!r} (not on the GPU machine: hidden by "
                                  "scripts/device_sim for the dry run)", name=fullname)


def _hidden_dist(name: str) -> bool:
    return name.replace("-", "_").lower() in {h.lower() for h in _HIDE}


_distribution = importlib.metadata.distribution


def _device_distribution(name):
    dist = _distribution(name)
    if _hidden_dist(name) and not _allowed(str(dist.locate_file(""))):
        raise importlib.metadata.PackageNotFoundError(name)
    return dist


if _HIDE:
    sys.meta_path.insert(0, _DeviceOnlyFinder())
    importlib.metadata.distribution = _device_distribution
