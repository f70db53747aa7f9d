"""Packaging: one version source, console scripts, type information, the OpenCV choice. The wheel itself is
checked by ``make check-wheel`` (fresh venv, README quickstart from an empty folder)."""

import importlib
import os
import subprocess
import sys

import pytest

import torchpf

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _pyproject():
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        return tomllib.load(f)


def _run(*args, **kw):
    env = {**os.environ, "PYTHONPATH": ROOT}
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, cwd=ROOT, **kw)


def test_one_version_source():
    meta = _pyproject()
    assert meta["project"]["dynamic"] == ["version"] and "version" not in meta["project"]
    assert meta["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "torchpf._version.__version__"}
    for module in ("torchpf", "training"):
        out = _run("-m", module, "--version")
        assert out.returncode == 0 and out.stdout.strip() == f"torchpf {torchpf.__version__}", out
    with open(os.path.join(ROOT, "CHANGELOG.md"), encoding="utf-8") as f:
        assert torchpf.__version__ in f.read()


def test_console_scripts_typing_and_license():
    meta = _pyproject()
    for name, target in meta["project"]["scripts"].items():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), name
    assert set(meta["project"]["scripts"]) == {"torchpf", "torchpf-train"}
    data = meta["tool"]["setuptools"]["package-data"]
    for package in ("torchpf", "priors", "training"):
        assert os.path.exists(os.path.join(ROOT, package, "py.typed")) and "py.typed" in data[package]
    assert os.path.exists(os.path.join(ROOT, "LICENSE"))
    deps = meta["project"]["dependencies"]
    assert not any(d.startswith("opencv") for d in deps), "users choose their OpenCV build (README)"
    assert all(">=" in d for d in deps), "every dependency has the lower bound the suite ran with"


@pytest.mark.parametrize("present", [True, False])
def test_import_warns_only_without_opencv(present):
    hide = "" if present else "import sys; sys.modules['cv2'] = None; "
    out = _run("-W", "always", "-c", hide + "import torchpf")
    assert out.returncode == 0, out.stderr
    assert ("torchpf[opencv]" in out.stderr) is not present, out.stderr
