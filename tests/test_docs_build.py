"""The docs site builds with ``mkdocs build --strict``: every page in the nav, every link and anchor resolves, and
the API reference's docstrings render (mkdocstrings). CI runs it with the rest of the tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_mkdocs_build_strict(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    # no -q: it drops the warnings before strict mode counts them (a build with griffe warnings passed that way)
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                           "-d", str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env=env)
    assert done.returncode == 0, done.stderr[-4000:]
    assert "WARNING" not in done.stderr, done.stderr[-4000:]
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    for role in (":func:", ":class:", ":mod:", ":data:", ":meth:"):  # Sphinx roles render as code, not text
        assert role + "<code>" not in api, role
    assert "run_trial" in api and "LoopBackend" in api and "load_robot_config" in api
    for page in ("index.html", "cli/index.html", "harness/index.html", "perception/index.html"):
        assert (tmp_path / "site" / page).exists(), page
