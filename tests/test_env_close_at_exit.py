"""Envs left open close their GL contexts at interpreter exit without EGL tracebacks (torm.runtime.close_at_exit)."""

from __future__ import annotations

import os
import subprocess
import sys

SCRIPT = """
import gymnasium as gym
import torm.env  # registers the ids
e = gym.make("torm/TormGraspSelect-v0", render_mode="rgb_array")
e.reset(seed=0)
assert e.render().ndim == 3
p = gym.make("torm/TormPick-v0", cameras=("overview",))
p.reset(seed=0)
print("left open")
"""


def test_envs_left_open_exit_without_tracebacks():
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "MUJOCO_GL": "egl"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert "left open" in done.stdout
    assert "Traceback" not in done.stderr and "EGLError" not in done.stderr, done.stderr[-3000:]
