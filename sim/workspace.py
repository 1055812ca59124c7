"""The simulated cell's fixed geometry, shared by the world, the camera rig and the robot loader (m, world frame).

The world frame has z up with the table top at z = 0; the robot base stands at the origin.
"""

from __future__ import annotations

import numpy as np

#: z of the table top surface (m).
TABLE_HEIGHT = 0.0
#: The reconstruction box the objects stand in: [[x_min, y_min, z_min], [x_max, y_max, z_max]] (m).
WORKSPACE_BOUNDS = np.array([[0.33, -0.22, -0.005], [0.77, 0.22, 0.20]])

__all__ = ["TABLE_HEIGHT", "WORKSPACE_BOUNDS"]
