"""A gripper's measured grip-force map: requested pad force (N) -> actuator force-limit setting, per opening width.

The same actuator force limit gives different pad forces on different grippers (a linkage multiplies or
divides it, and by how much depends on the finger angle, i.e. on the width the fingers stop at). So each
gripper carries a table measured in simulation on fixed blocks (``python -m sim.robots.measure_gripper ROBOT
--force``): for every block width and every tried setting, the pad force MuJoCo's contact solver reports.
The backend inverts it to command a pad force in newtons. :func:`measured_pad_force` is the measurement, used
by the measuring tool, the tests and the trial record alike.

Definitions. *Pad force*: the normal force one finger's pads press on the object (N), averaged over the two
fingers (for a balanced parallel grasp both are equal). *Setting*: the symmetric force limit
``actuator_forcerange = (-s, s)`` of the gripper actuator, in the actuator's own force units (N for a slide or
tendon drive, N m for a hinge drive).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from torm.errors import ConfigError


@dataclass(frozen=True)
class ForceMap:
    """Measured pad force on a grid of (block width, actuator setting).

    Attributes:
        widths: (W,) block widths the map was measured on (m), strictly increasing.
        settings: (S,) actuator force-limit settings tried (actuator force units), strictly increasing, > 0.
        pad_force: (W, S) measured pad force (N); each row non-decreasing with the setting (1 % slack). A row
            may level off: a position-servo gripper closing on a narrow block cannot reach its force limit (the
            servo's pull is stiffness x remaining travel); forces above a row's plateau are out of reach there.
        max_force: (W,) pad force (N) with the actuator's force limit removed, per width: the most the gripper
            can squeeze there (caps the interpolated rows); None = the rows' largest values.
    """

    widths: tuple[float, ...]
    settings: tuple[float, ...]
    pad_force: tuple[tuple[float, ...], ...]
    max_force: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        w, s = np.asarray(self.widths, float), np.asarray(self.settings, float)
        f = np.asarray(self.pad_force, float)
        if len(w) < 1 or len(s) < 2:
            raise ConfigError("gripper.force_map needs at least one width and two settings")
        if np.any(np.diff(w) <= 0) or np.any(w <= 0):
            raise ConfigError(f"gripper.force_map.widths must be positive and strictly increasing (m), got {list(w)}")
        if np.any(np.diff(s) <= 0) or np.any(s <= 0):
            raise ConfigError(f"gripper.force_map.settings must be positive and strictly increasing, got {list(s)}")
        if f.shape != (len(w), len(s)):
            raise ConfigError(f"gripper.force_map.pad_force must be {len(w)} rows (widths) of {len(s)} values "
                              f"(settings), got shape {f.shape}")
        if self.max_force is not None and (len(self.max_force) != len(w) or min(self.max_force) <= 0):
            raise ConfigError(f"gripper.force_map.max_force needs {len(w)} positive values (N), one per width")
        drop = np.maximum.accumulate(f, axis=1) - f
        # a row may be flat from its first setting only where that is already the most the gripper squeezes there
        # (a position servo on a narrow block: its max_force); every other row must rise at first
        saturated = (np.asarray(self.max_force, float) * 0.99 <= f[:, 0] if self.max_force is not None
                     else np.zeros(len(w), bool))
        if np.any(f < 0) or np.any(drop > 0.01 * np.maximum(f, 1.0)) or np.any((f[:, 1] <= f[:, 0]) & ~saturated):
            raise ConfigError("gripper.force_map.pad_force must be >= 0 and grow with the setting in every row "
                              "(rising from the first to the second setting); re-measure with "
                              "python -m sim.robots.measure_gripper ROBOT --force")

    def _row(self, width_m: float) -> np.ndarray:
        """(S,) pad force (N) per setting at ``width_m`` (linear in width, clamped to the measured widths)."""
        f = np.asarray(self.pad_force, float)
        w = np.asarray(self.widths, float)
        row = f[0] if len(w) == 1 else np.array([np.interp(width_m, w, f[:, j]) for j in range(f.shape[1])])
        if self.max_force is not None:
            row = np.minimum(row, float(np.interp(width_m, w, np.asarray(self.max_force, float))))
        return row

    def _rising(self, width_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(settings, forces) of the row at ``width_m`` up to where it levels off (forces strictly increasing)."""
        row, s = self._row(width_m), np.asarray(self.settings, float)
        keep = [0]
        for i in range(1, len(row)):
            if row[i] > row[keep[-1]] * 1.005 + 1e-9:
                keep.append(i)
        return s[keep], row[keep]

    def force_range(self, width_m: float) -> tuple[float, float]:
        """Smallest and largest pad force (N) the measured settings produce at ``width_m`` (m)."""
        _, f = self._rising(width_m)
        return float(f[0]), float(f[-1])

    def pad_force_at(self, setting: float, width_m: float) -> float:
        """Pad force (N) that actuator ``setting`` produces at ``width_m`` (m), interpolated."""
        return float(np.interp(setting, np.asarray(self.settings, float), self._row(width_m)))

    def setting_for(self, pad_force_n: float, width_m: float) -> float:
        """Actuator setting that produces ``pad_force_n`` (N) at ``width_m`` (m); clamped to the rising part of
        the measured range (above a plateau: the setting where it starts)."""
        s, f = self._rising(width_m)
        return float(np.interp(pad_force_n, f, s))


def pad_distance(model: mujoco.MjModel, data: mujoco.MjData, left: Sequence[int], right: Sequence[int],
                 distmax: float = 1.0) -> float:
    """Smallest signed distance (m) between a left and a right pad geom (negative = interpenetrating).

    Exact for any pad shapes (``mj_geomDistance``); ``data`` must hold current geom poses (mj_kinematics).
    """
    return float(min(mujoco.mj_geomDistance(model, data, int(a), int(b), distmax, None)
                     for a in left for b in right))


def measured_pad_force(model: mujoco.MjModel, data: mujoco.MjData, left: Sequence[int], right: Sequence[int],
                       ignore: Collection[int] = ()) -> float:
    """Pad force (N) in ``data``: per finger, the summed normal force of the contacts between its pad geoms and
    any geom not in ``ignore`` (MuJoCo's contact forces, ``mj_contactForce``); the mean of the two fingers."""
    sides = (set(int(g) for g in left), set(int(g) for g in right))
    totals = [0.0, 0.0]
    f6 = np.zeros(6)
    skip = set(int(g) for g in ignore)
    for i, c in enumerate(data.contact[: data.ncon]):
        g1, g2 = int(c.geom1), int(c.geom2)
        for k, pads in enumerate(sides):
            other = g2 if g1 in pads else g1 if g2 in pads else None
            if other is None or other in skip or other in sides[0] or other in sides[1]:
                continue
            mujoco.mj_contactForce(model, data, i, f6)
            totals[k] += float(f6[0])
    return 0.5 * (totals[0] + totals[1])
