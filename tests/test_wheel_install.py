"""The distribution a user installs: ``python -m build`` makes a wheel and an sdist of ``torm-glass``; the wheel,
installed with an extra into a fresh virtual environment (dependencies from the package registry, torch from the
tested CPU wheel), imports ``torm``, carries its package data (robots, scenes, segmentation models) and runs a smoke
trial. What this guards: a file left out of the package data, an import of something only the dev extra installs,
a console script that does not start.

Slow (a venv and an install: about 1-3 minutes with pip's cache warm); marked ``slow``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.slow]


def _run(cmd: list[str], cwd: Path, timeout: float, env: dict[str, str] | None = None) -> str:
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})
    assert done.returncode == 0, f"{' '.join(cmd)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_the_built_wheel_installs_in_a_fresh_venv_and_runs_a_smoke_trial(tmp_path):
    pytest.importorskip("build", reason="the dev extra installs 'build'")
    dist = tmp_path / "dist"
    # --no-isolation: the build backend (setuptools, wheel) of this environment, no download for the build itself
    _run([sys.executable, "-m", "build", "--no-isolation", "--wheel", "--sdist", "--outdir", str(dist)], ROOT, 600)
    wheels = sorted(dist.glob("torm_glass-*.whl"))
    assert wheels and sorted(dist.glob("torm_glass-*.tar.gz")), sorted(p.name for p in dist.iterdir())
    names = set(zipfile.ZipFile(wheels[0]).namelist())
    for needed in ("torm/segmentation/models/learned_seg.onnx", "sim/scenes/suites/rw.yaml",
                   "torm/segmentation/models/learned_seg_v4.onnx"):
        assert needed in names, needed
    assert any(n.startswith("sim/robots/") and n.endswith(".xml") for n in names)
    assert not any(n.startswith("tests/") for n in names)

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], tmp_path, 300)
    py = str(venv / "bin" / "python")
    import torch

    # the torch this suite runs on (CI: the CPU wheel on disk), then the wheel with an extra from the registry
    _run([py, "-m", "pip", "install", "-q", f"torch=={torch.__version__.split('+')[0]}"], tmp_path, 900)
    _run([py, "-m", "pip", "install", "-q", f"{wheels[0]}[train]"], tmp_path, 900)
    out = _run([py, "-c", "import importlib.metadata as m, torm, efficientnet_lite_pytorch; "
                "print(m.version('torm-glass'), torm.__file__)"], tmp_path, 120)
    assert str(venv) in out.split()[1], out  # the installed wheel, not this checkout
    res = _run([str(venv / "bin" / "torm"), "trial", "--scenario", "rw1", "--seed", "0", "--method", "oracle",
                "--set", "capture.n_views=4", "--json"], tmp_path, 900, {"MUJOCO_GL": "egl"})
    record = json.loads(res)
    assert record["scenario"] == "rw1" and record["n_objects"] == 1, {k: record.get(k) for k in ("scenario",)}


def test_the_distribution_name_is_the_one_the_code_reads():
    """``torm.bench.identity`` reads torm's requirements by distribution name: it must be pyproject's."""
    import re

    from torm.bench.identity import DISTRIBUTION

    name = re.search(r'^name = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M)
    assert name and name.group(1) == DISTRIBUTION
