"""scripts/install.sh decides where splatzoo goes (checked with --dry-run and a stub interpreter, so nothing is
installed), the README's set-up is what CI runs, and each checkout and environment gets its own native build."""
from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "install.sh"

# what the stub interpreter says about itself: Debian's /usr/bin/python3 unless a test says otherwise
SYSTEM_PYTHON = dict(version="3.11.2", minor="3.11", new_enough=1, executable="/usr/bin/python3", prefix="/usr",
                     base_prefix="/usr", venv=0, conda=0, managed=1, ensurepip=1, pip=1, headers=1)


def _executable(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return path


@pytest.fixture
def dry_run(tmp_path):
    """Run a copy of install.sh --dry-run in an empty checkout, with a stub python (answers the script's questions
    about itself, records every call, runs nothing) and stub apt-get and id on PATH."""
    checkout = tmp_path / "checkout"
    (checkout / "scripts").mkdir(parents=True)
    shutil.copy(SCRIPT, checkout / "scripts" / "install.sh")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log = tmp_path / "calls.log"
    py = _executable(bin_dir / "python3", '#!/bin/sh\necho "python $*" >> "$STUB_LOG"\n'
                     'if [ "$1" = - ]; then cat >/dev/null; printf "%s\\n" "$STUB_FACTS"; exit 0; fi\nexit 1\n')
    _executable(bin_dir / "apt-get", '#!/bin/sh\necho "apt-get $*" >> "$STUB_LOG"\nexit 1\n')
    _executable(bin_dir / "id", '#!/bin/sh\necho 0\n')  # root: apt-get runs without sudo

    def run(*args: str, env: dict | None = None, **facts):
        env = {**{k: v for k, v in os.environ.items() if k != "TORCH_VERSION"}, **(env or {}),
               "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "PYTHON": str(py), "STUB_LOG": str(log),
               "STUB_FACTS": "\n".join(f"{k}={v}" for k, v in {**SYSTEM_PYTHON, **facts}.items())}
        r = subprocess.run(["bash", str(checkout / "scripts" / "install.sh"), "--dry-run", *args], cwd=checkout,
                           env=env, capture_output=True, text=True, timeout=60)
        calls = log.read_text().splitlines() if log.exists() else []
        log.unlink(missing_ok=True)
        # a dry run only asks: no venv made, nothing installed, apt-get never run
        assert not [c for c in calls if not c.startswith("python") or "-m venv" in c or "-m pip" in c], calls
        return r

    run.checkout, run.py = checkout, py
    return run


def test_the_system_python_gets_a_venv_in_the_checkout(dry_run):
    r = dry_run()
    assert r.returncode == 0, r.stderr
    venv = dry_run.checkout / ".venv"
    assert "externally managed (PEP 668)" in r.stdout and f"goes into the virtual environment {venv}" in r.stdout
    assert f"would run: {dry_run.py} -m venv {venv}" in r.stdout
    lines = r.stdout.splitlines()
    pip = [i for i, line in enumerate(lines) if "-m pip install" in line]
    assert [lines[i].split("would run: ")[1].split(" -m pip")[0] for i in pip] == [f"{venv}/bin/python"] * 3
    # torch, pinned, comes before the package that asks for it
    assert "torch==2.13.0" in lines[pip[0]] and "-e .[mesh,viewer,dev]" in lines[pip[1]]
    assert [f"[{i}/6]" for i in range(1, 7)] == [line.split()[0] for line in lines if line.startswith("[")]
    assert "source .venv/bin/activate" not in r.stdout  # a dry run makes nothing to activate
    # the C++ rasterizer is built by the set-up, in the environment, not by the first render (or test)
    assert any(line.split("would run: ")[-1].startswith(f"{venv}/bin/python -c from splatzoo.rasterizers import "
                                                        "available_backends") for line in lines), r.stdout


def test_an_interpreter_outside_any_environment_also_gets_the_venv(dry_run):
    r = dry_run(managed=0, executable="/opt/python/bin/python3", prefix="/opt/python", base_prefix="/opt/python")
    assert r.returncode == 0, r.stderr
    assert f"goes into the virtual environment {dry_run.checkout / '.venv'}" in r.stdout
    assert "externally managed" not in r.stdout


@pytest.mark.parametrize("kind, facts", [("active virtual environment", dict(venv=1)),
                                         ("conda environment", dict(conda=1, base_prefix="/env/x"))])
def test_an_active_venv_or_conda_env_is_installed_into(dry_run, kind, facts):
    r = dry_run(managed=0, prefix="/env/x", **facts)
    assert r.returncode == 0, r.stderr
    assert f"goes into the {kind} /env/x" in r.stdout
    assert "-m venv" not in r.stdout and ".venv" not in r.stdout
    assert f"would run: {dry_run.py} -m pip install torch==2.13.0" in r.stdout


def test_no_venv_installs_into_the_interpreter_unless_it_is_externally_managed(dry_run):
    r = dry_run("--no-venv")
    assert r.returncode == 1 and "externally managed (PEP 668)" in r.stderr and "[1/6]" not in r.stdout
    r = dry_run("--no-venv", managed=0, base_prefix="/opt/python")
    assert r.returncode == 0, r.stderr
    assert "goes into the interpreter itself" in r.stdout and "-m venv" not in r.stdout
    assert f"would run: {dry_run.py} -m pip install -e .[mesh,viewer,dev]" in r.stdout


def test_missing_venv_support_is_installed_with_apt_or_explained(dry_run):
    r = dry_run(ensurepip=0, headers=0)
    assert r.returncode == 0, r.stderr
    assert re.search(r"would run: env DEBIAN_FRONTEND=noninteractive apt-get install .*python3\.11-dev "
                     r"python3\.11-venv$", r.stdout, re.M), r.stdout
    # an interpreter that is not the distribution's: apt cannot help, so say what to do
    r = dry_run(ensurepip=0, executable="/opt/python/bin/python3", prefix="/opt/python", base_prefix="/opt/python",
                managed=0)
    assert r.returncode == 1 and "cannot make a virtual environment" in r.stderr, r.stderr


def test_refusals_say_why(dry_run):
    r = dry_run(version="3.10.12", minor="3.10", new_enough=0)
    assert r.returncode == 1 and "needs Python 3.11 or newer" in r.stderr and "3.10.12" in r.stderr
    (dry_run.checkout / ".venv").mkdir()
    r = dry_run()
    assert r.returncode == 1 and "is not a virtual environment" in r.stderr
    r = subprocess.run(["bash", str(SCRIPT), "--bogus"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "unknown option --bogus" in r.stderr


def test_torch_version_sets_the_pin(dry_run):
    r = dry_run(env={"TORCH_VERSION": "2.9.1"})
    assert r.returncode == 0, r.stderr
    assert "-m pip install torch==2.9.1" in r.stdout and "torch==2.13.0" not in r.stdout


def test_the_readme_set_up_is_what_ci_runs():
    readme = (REPO / "README.md").read_text()
    quick = re.search(r"## Quick start\n+```bash\n(.*?)```", readme, re.S).group(1)
    commands = [line.split("#")[0].strip() for line in quick.splitlines() if line.strip()]
    assert commands[:2] == ["bash scripts/install.sh", "source .venv/bin/activate"]
    ci = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()
          if line.strip() and not line.startswith(("#", "set ", "cd ", "apt-get ", "export "))]
    assert "python3 -m pytest -q" in ci, ci
    main = ci[:ci.index("python3 -m pytest -q") + 1]  # the README's set-up and test command, in its order
    set_up_and_tests = [c for c in commands if c in main]
    assert set_up_and_tests == main, (main, commands)
    # then only the nerfstudio methods' own environment and tests (docs/nerfstudio.md)
    extras = ci[len(main):]
    assert all(c == "deactivate" or "nerfstudio" in c for c in extras), extras


def test_the_venv_is_not_tracked():
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    r = subprocess.run(["git", "check-ignore", "-q", ".venv/bin/python"], cwd=REPO)
    assert r.returncode == 0, ".venv is not ignored by .gitignore"


def test_the_native_build_cache_is_one_per_checkout_and_environment(monkeypatch, tmp_path):
    """The build files name the sources, torch and Python's headers by absolute path: a shared build name would have
    two checkouts (or two venvs) rebuild each other's extension on every switch."""
    from splatzoo.rasterizers import native

    name = native._build_name("cpu")
    assert native._build_name("cpu") == name
    other_checkout = tmp_path / "checkout" / "splatzoo" / "csrc"
    shutil.copytree(native.CSRC, other_checkout)  # the same sources, elsewhere
    elsewhere = {
        "another checkout": (native, "CSRC", other_checkout),
        "another environment's torch": (torch, "__file__", str(tmp_path / "venv/site-packages/torch/__init__.py")),
        "another torch version": (torch, "__version__", "0.0.1+other"),
        "another Python": (native.sys, "version", "3.12.1 (main) [GCC 12.2.0]"),
        "another Python's headers": (native.sysconfig, "get_paths", lambda: {"include": "/opt/py/include/python3.11"}),
    }
    for what, (obj, attr, value) in elsewhere.items():
        with monkeypatch.context() as m:
            m.setattr(obj, attr, value)
            assert native._build_name("cpu") != name, what
