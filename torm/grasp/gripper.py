"""Parallel-jaw gripper geometry (Robotiq-2F-85-like) as oriented boxes in the grasp frame.

Grasp frame (GraspNet): origin at the grasp centre (midway between the pads), x = approach direction
(pointing into the object), y = closing axis, z = finger height axis. Units: metres.

Along x the fingertips sit at ``x = depth`` (the grasp's GraspNet ``depth``), the pads span
``x in [depth - pad_length, depth]``, the fingers ``x in [depth - finger_length, depth]`` and the palm
(the gripper body plus the linkage) sits behind the fingers, ``x in [depth - finger_length - palm_depth,
depth - finger_length]``. The fingers' inner faces are at ``y = +-width / 2``.

The approach sweep is the volume the fingers and the palm pass through while moving from the pre-grasp
pose (``approach_distance`` back along -x) to the grasp: each sweep box is the finger / palm box
stretched back along -x by ``approach_distance`` (it contains the box itself).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from torm.errors import ConfigError

#: Order of the boxes returned by :meth:`GripperGeometry.boxes` (with ``include_sweep=True``).
BOX_NAMES: tuple[str, ...] = (
    "finger_left",  # -y side
    "finger_right",  # +y side
    "palm",
    "sweep_finger_left",
    "sweep_finger_right",
    "sweep_palm",
)

#: Indices (into ``BOX_NAMES``) whose union covers the whole gripper plus its approach sweep.
COLLISION_BOXES_WITH_SWEEP: tuple[int, ...] = (3, 4, 5)
#: Indices whose union covers the gripper at the grasp pose only.
COLLISION_BOXES_NO_SWEEP: tuple[int, ...] = (0, 1, 2)


@dataclass(frozen=True)
class GripperGeometry:
    """Collision geometry of a parallel-jaw gripper (defaults: Robotiq 2F-85), metres.

    The defaults equal the simulated Robotiq 2F-85 (``sim/robots/robotiq_2f85/2f85.xml``, the ``gripper.geometry``
    section of ``sim/robots/inovo_2f85/robot.yaml``): pads 22 x 6 x 37.5 mm centred on the TCP, finger boxes
    12 mm thick behind the pads reaching 47.5 mm behind the TCP, palm 75 x 90 x 95 mm behind the fingers.

    Attributes:
        max_opening: stroke, the largest inner distance between the pads (m).
        min_opening: smallest inner distance between the pads (m).
        pad_length: pad extent along the approach axis x (m) (2F-85: 37.5 mm).
        pad_width: pad extent along the finger-height axis z (m) (2F-85: 22 mm); also the finger's z extent.
        finger_thickness: finger (pad + finger) thickness along the closing axis y (m), from the pad face out.
        finger_length: finger extent along x from the fingertip back to the palm (m).
        palm_depth: palm box extent along x (m): gripper body and linkage behind the fingers.
        palm_width: palm box extent along y (m) (the fingers may stick out beyond it when open).
        palm_height: palm box extent along z (m).
        approach_distance: pre-grasp distance (m): the gripper starts this far back along -x and moves in.
        default_depth: fingertip position along x beyond the grasp centre (m), GraspNet's ``depth``;
            ``pad_length / 2`` centres the pads on the contacts.
    """

    max_opening: float = 0.085
    min_opening: float = 0.0
    pad_length: float = 0.0375
    pad_width: float = 0.022
    finger_thickness: float = 0.018
    finger_length: float = 0.06625
    palm_depth: float = 0.095
    palm_width: float = 0.09
    palm_height: float = 0.075
    approach_distance: float = 0.10
    default_depth: float = 0.01875

    def __post_init__(self) -> None:
        for name in ("max_opening", "pad_length", "pad_width", "finger_thickness", "finger_length", "palm_depth",
                     "palm_width", "palm_height"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"GripperGeometry.{name} must be a positive number of metres, got {v}")
        for name in ("min_opening", "approach_distance", "default_depth"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ConfigError(f"GripperGeometry.{name} must be a non-negative number of metres, got {v}")
        if self.min_opening >= self.max_opening:
            raise ConfigError(
                f"GripperGeometry.min_opening ({self.min_opening}) must be below max_opening ({self.max_opening})"
            )
        if self.pad_length > self.finger_length:
            raise ConfigError(
                f"GripperGeometry.pad_length ({self.pad_length}) cannot exceed finger_length ({self.finger_length})"
            )
        if self.default_depth > self.finger_length:
            raise ConfigError(
                f"GripperGeometry.default_depth ({self.default_depth}) cannot exceed finger_length "
                f"({self.finger_length}): the palm would sit in front of the grasp centre"
            )

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None) -> GripperGeometry:
        """Build from a robot config's gripper-geometry section (keys = field names, metres).

        Unknown keys raise :class:`~torm.errors.ConfigError` listing the valid keys.
        """
        from torm.config import from_dict

        return from_dict(cls, dict(data or {}), where="gripper geometry")

    @classmethod
    def from_robot_config(cls, geometry: Mapping[str, Any], approach_distance: float = 0.10,
                          min_opening: float = 0.0) -> GripperGeometry:
        """Build from a robot config's ``gripper.geometry`` section in the TCP-frame box schema.

        Schema (full box extents ``[x, y, z]`` in the TCP frame, metres; see sim/robots/inovo_2f85/README.md):
        ``approach_axis``, ``closing_axis`` (``x``/``y``/``z``), ``pad_size``, ``finger_size`` (the finger box
        behind each pad, outward along the closing axis), ``finger_center_approach``, ``palm_size``,
        ``palm_center_approach``, ``max_opening``, ``finger_depth``, ``tip_approach``. Unknown or missing keys
        raise :class:`~torm.errors.ConfigError`. The finger thickness is pad + finger box; a palm that starts
        behind the fingers is extended forward to them (conservative).
        """
        keys = {"approach_axis", "closing_axis", "pad_size", "finger_size", "finger_center_approach", "palm_size",
                "palm_center_approach", "max_opening", "finger_depth", "tip_approach"}
        got = set(geometry)
        if got != keys:
            raise ConfigError(f"gripper geometry: unknown key(s) {sorted(got - keys)} and missing key(s) "
                              f"{sorted(keys - got)}; valid keys: {sorted(keys)}")
        axes = {"x": 0, "y": 1, "z": 2}
        try:
            a, c = axes[geometry["approach_axis"]], axes[geometry["closing_axis"]]
        except KeyError as exc:
            raise ConfigError(f"gripper geometry: axes must be one of x, y, z, got {exc}") from exc
        if a == c:
            raise ConfigError("gripper geometry: approach_axis and closing_axis must differ")
        h = 3 - a - c
        try:
            pad, finger, palm = (np.asarray(geometry[k], dtype=float).reshape(3)
                                 for k in ("pad_size", "finger_size", "palm_size"))
            tip = float(geometry["tip_approach"])
            fl = float(geometry["finger_depth"])
            finger_back = float(geometry["finger_center_approach"]) - finger[a] / 2
            palm_front = float(geometry["palm_center_approach"]) + palm[a] / 2
            palm_back = float(geometry["palm_center_approach"]) - palm[a] / 2
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"gripper geometry: sizes must be [x, y, z] lists of metres ({exc})") from exc
        if abs((tip - fl) - finger_back) > 1e-3:
            raise ConfigError(f"gripper geometry: finger box ends at {finger_back:.4f} m along the approach but "
                              f"tip_approach - finger_depth is {tip - fl:.4f} m; make them agree")
        if palm_front > tip - fl + 1e-3:
            raise ConfigError(f"gripper geometry: the palm box reaches {palm_front:.4f} m along the approach, in "
                              f"front of the fingers' back end ({tip - fl:.4f} m); this model puts it behind them")
        def r(v: float) -> float:  # drop float noise from the sums (nm resolution)
            return round(float(v), 9)

        return cls(max_opening=r(geometry["max_opening"]), min_opening=min_opening, pad_length=r(pad[a]),
                   pad_width=r(max(pad[h], finger[h])), finger_thickness=r(pad[c] + finger[c]),
                   finger_length=r(fl), palm_depth=r((tip - fl) - palm_back), palm_width=r(palm[c]),
                   palm_height=r(palm[h]), approach_distance=approach_distance, default_depth=r(tip))

    # ------------------------------------------------------------------ boxes
    def box_params(self, width: np.ndarray | float, depth: np.ndarray | float | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned (in the grasp frame) box centres and half extents for a batch of openings.

        Args:
            width: (C,) or scalar opening between the pads' inner faces (m).
            depth: (C,) or scalar fingertip position along x (m); ``default_depth`` when None.

        Returns:
            centres (C, 6, 3) and half extents (C, 6, 3) in the grasp frame, boxes in ``BOX_NAMES`` order.
        """
        w = np.atleast_1d(np.asarray(width, dtype=np.float64))
        d = np.atleast_1d(np.asarray(self.default_depth if depth is None else depth, dtype=np.float64))
        w, d = np.broadcast_arrays(w, d)
        C = w.shape[0]
        t, fl, a = self.finger_thickness, self.finger_length, self.approach_distance
        centres = np.zeros((C, 6, 3))
        halves = np.zeros((C, 6, 3))
        finger_x = d - fl / 2
        finger_y = w / 2 + t / 2
        palm_x = d - fl - self.palm_depth / 2
        fz = self.pad_width / 2
        pz = self.palm_height / 2
        # fingers
        centres[:, 0] = np.stack([finger_x, -finger_y, np.zeros(C)], -1)
        centres[:, 1] = np.stack([finger_x, finger_y, np.zeros(C)], -1)
        halves[:, 0:2] = [fl / 2, t / 2, fz]
        # palm
        centres[:, 2, 0] = palm_x
        halves[:, 2] = [self.palm_depth / 2, self.palm_width / 2, pz]
        # sweeps: the same boxes stretched back along -x by the approach distance
        centres[:, 3] = centres[:, 0] - [a / 2, 0.0, 0.0]
        centres[:, 4] = centres[:, 1] - [a / 2, 0.0, 0.0]
        centres[:, 5] = centres[:, 2] - [a / 2, 0.0, 0.0]
        halves[:, 3:5] = [fl / 2 + a / 2, t / 2, fz]
        halves[:, 5] = [self.palm_depth / 2 + a / 2, self.palm_width / 2, pz]
        return centres, halves

    def boxes(self, width: float, depth: float | None = None, include_sweep: bool = True,
              ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The gripper's collision boxes in the grasp frame for one opening ``width`` (m).

        Returns a list of ``(T_grasp_box (4, 4), half_extents (3,))`` in ``BOX_NAMES`` order: left finger,
        right finger, palm and (when ``include_sweep``) the three approach-sweep boxes.
        """
        c, h = self.box_params(width, depth)
        n = 6 if include_sweep else 3
        out = []
        for i in range(n):
            T = np.eye(4)
            T[:3, 3] = c[0, i]
            out.append((T, h[0, i].copy()))
        return out

    def reach_radius(self) -> float:
        """Radius (m) of a sphere around the grasp centre that holds every box (sweep included) at any opening."""
        c, h = self.box_params(self.max_opening, self.finger_length)
        c2, h2 = self.box_params(self.max_opening, 0.0)
        r1 = np.linalg.norm(np.abs(c[0]) + h[0], axis=-1).max()
        r2 = np.linalg.norm(np.abs(c2[0]) + h2[0], axis=-1).max()
        return float(max(r1, r2))
