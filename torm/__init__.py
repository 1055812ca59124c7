"""TORM: transparent-object reconstruction and manipulation from multi-view silhouettes.

Units: metres, radians, seconds, kilograms. World frame = robot base frame, z up.
Camera poses follow the OpenCV convention (x right, y down, z forward).
"""

from __future__ import annotations

__version__ = "0.1.0"
