"""TORM: transparent-object reconstruction and manipulation from multi-view silhouettes.

Units: metres, radians, seconds, kilograms. World frame = robot base frame, z up.
Camera poses follow the OpenCV convention (x right, y down, z forward).
"""

from __future__ import annotations

__version__ = "0.1.0"

# Importing torm registers the gymnasium envs (torm/TormPick-v0, torm/TormGraspSelect-v0): string entry
# points only, so this imports gymnasium but none of the simulator.
from torm.env import register_envs as _register_envs  # noqa: E402

_register_envs()
