"""Test-wide settings: headless rendering and one torch thread per test process."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import torch  # noqa: E402

torch.set_num_threads(max(1, min(2, len(os.sched_getaffinity(0)))))
