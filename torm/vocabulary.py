"""The names the command line and the configs share, in one light module (no numpy, torch or MuJoCo import).

Every command that takes a method, segmenter, renderer, depth model or realism profile offers these choices; the
modules that implement them (:mod:`torm.pipeline`, :mod:`torm.segmentation`, :mod:`torm.bench.spec`) re-export
them, so there is one definition. Keeping this module free of heavy imports lets ``torm --help`` answer without
loading torch.
"""

from __future__ import annotations

from pathlib import Path

#: Built-in perception methods (plug-ins register more: :mod:`torm.methods`).
METHODS: tuple[str, ...] = ("torm", "depth", "depth_fusion", "oracle")
#: Silhouette sources (``segmentation.segmenter``).
SEGMENTERS: tuple[str, ...] = ("gt", "noisy", "grounded_sam", "learned", "difference")
#: RGB renderers of the simulated camera (``capture.renderer``).
RENDERERS: tuple[str, ...] = ("mujoco", "pbr")
#: Sensor-depth models of the simulated depth camera (``capture.depth_model``).
DEPTH_MODELS: tuple[str, ...] = ("ideal", "statistical", "stereo")
#: Realism profiles of the simulated world (``world.realism``).
REALISM_PROFILES: tuple[str, ...] = ("ideal", "measured", "stress")
#: Factor groups of a realism profile (``world.factors``; empty = all of them).
REALISM_FACTORS: tuple[str, ...] = ("contact", "grip_force", "objects", "calibration", "execution")
#: Object classes a segmentation prompt may name (``learned.classes``, a scenario's ``targets``).
CLASSES: tuple[str, ...] = ("transparent", "opaque")
#: Benchmark engines (``torm bench --engine``) and rerun recording modes of a bench (``--record``).
ENGINES: tuple[str, ...] = ("pool", "ray")
RECORD_MODES: tuple[str, ...] = ("none", "failures", "all")
START_METHODS: tuple[str, ...] = ("forkserver", "spawn")

_SUITES_DIR = Path(__file__).resolve().parents[1] / "sim" / "scenes" / "suites"


def suite_names() -> list[str]:
    """Scenario suite names (the YAML files of ``sim/scenes/suites``), without importing the scene library."""
    return sorted(p.stem for p in _SUITES_DIR.glob("*.yaml"))
