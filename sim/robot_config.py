"""Robot configs: which MJCF, which joints/actuators/sites, limits and gripper geometry, from one YAML.

A robot folder ``sim/robots/<name>/`` holds a ``robot.yaml`` that names everything the harness needs
from its MJCF, so a third-party arm or gripper is plugged in with only a YAML (pass its path to
:func:`load_robot_config`). Units: m, rad, s, kg, N. Frames: world = robot base frame, z up; the
gripper geometry is given in the TCP frame (origin at the pinch point midway between the pad
centres, ``approach_axis`` pointing out of the flange towards the fingertips, ``closing_axis``
along which the pads move).

Paths in the YAML (``mjcf``, ``scene``) are relative to the YAML's folder and are resolved to
absolute paths on load.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np

from torm.config import from_dict, load_yaml
from torm.errors import ConfigError, SceneError, UnknownNameError

log = logging.getLogger(__name__)

ROBOTS_DIR = Path(__file__).resolve().parent / "robots"
ROBOT_YAML = "robot.yaml"

Axis = Literal["x", "y", "z"]


@dataclass(frozen=True)
class ArmConfig:
    """The arm: joint/actuator names (same order), TCP and flange sites, limits and the home pose.

    Attributes:
        joints: arm joint names in kinematic order (n).
        actuators: position actuators driving ``joints``, same order (n); ctrl = joint target (rad).
        flange_site: site at the tool flange (gripper mounting face).
        tcp_site: site at the tool centre point (pinch point of the gripper).
        position_limits: (n, 2) [lower, upper] joint limits (rad), within the MJCF joint ranges.
        velocity_limits: (n,) joint speed limits (rad/s).
        acceleration_limits: (n,) joint acceleration limits (rad/s^2).
        home: (n,) "ready" joint configuration (rad).
    """

    joints: tuple[str, ...]
    actuators: tuple[str, ...]
    flange_site: str
    tcp_site: str
    position_limits: tuple[tuple[float, float], ...]
    velocity_limits: tuple[float, ...]
    acceleration_limits: tuple[float, ...]
    home: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.joints)
        if n == 0:
            raise ConfigError("arm.joints is empty; list the arm's joint names in kinematic order")
        if len(set(self.joints)) != n:
            raise ConfigError(f"arm.joints has duplicates: {list(self.joints)}")
        for name in ("actuators", "position_limits", "velocity_limits", "acceleration_limits", "home"):
            if len(getattr(self, name)) != n:
                raise ConfigError(f"arm.{name} has {len(getattr(self, name))} entries but arm.joints has {n}; "
                                  "give one per joint, in the same order")
        for j, (lo, hi) in zip(self.joints, self.position_limits, strict=True):
            if not lo < hi:
                raise ConfigError(f"arm.position_limits for {j!r}: lower {lo} must be below upper {hi} (rad)")
        for name in ("velocity_limits", "acceleration_limits"):
            bad = [j for j, v in zip(self.joints, getattr(self, name), strict=True) if not v > 0]
            if bad:
                raise ConfigError(f"arm.{name} must be positive; check joints {bad}")
        outside = [j for j, q, (lo, hi) in zip(self.joints, self.home, self.position_limits, strict=True)
                   if not lo <= q <= hi]
        if outside:
            raise ConfigError(f"arm.home is outside arm.position_limits for joints {outside}")

    @property
    def lower(self) -> np.ndarray:
        """(n,) lower joint limits (rad)."""
        return np.array([lo for lo, _ in self.position_limits])

    @property
    def upper(self) -> np.ndarray:
        """(n,) upper joint limits (rad)."""
        return np.array([hi for _, hi in self.position_limits])

    @property
    def home_q(self) -> np.ndarray:
        """(n,) home joint configuration (rad)."""
        return np.array(self.home)


@dataclass(frozen=True)
class GripperGeometry:
    """Box approximation of the gripper for grasp-planner collision checks, in the TCP frame (m).

    Sizes are full extents ``[x, y, z]`` of the TCP frame's axes. The pads sit at
    ``+-(opening / 2 + pad_size[closing] / 2)`` along ``closing_axis`` and centred on the TCP along
    ``approach_axis``; each finger box lies directly behind its pad (further from the TCP along the
    closing axis) with its centre at ``finger_center_approach`` along the approach axis; the palm box is
    centred on the approach axis at ``palm_center_approach`` (negative = towards the flange).

    Attributes:
        approach_axis: TCP-frame axis pointing from the palm towards the fingertips.
        closing_axis: TCP-frame axis along which the pads move.
        pad_size: full extents of one pad box (m).
        finger_size: full extents of one finger box behind its pad (m).
        finger_center_approach: finger box centre along the approach axis (m).
        palm_size: full extents of the palm box (m).
        palm_center_approach: palm box centre along the approach axis (m).
        max_opening: largest gap between the pads (m).
        finger_depth: fingertip to palm face along the approach axis (m): how deep an object can go.
        tip_approach: fingertip position along the approach axis (m).
    """

    approach_axis: Axis
    closing_axis: Axis
    pad_size: tuple[float, float, float]
    finger_size: tuple[float, float, float]
    finger_center_approach: float
    palm_size: tuple[float, float, float]
    palm_center_approach: float
    max_opening: float
    finger_depth: float
    tip_approach: float

    def __post_init__(self) -> None:
        if self.approach_axis == self.closing_axis:
            raise ConfigError("gripper.geometry: approach_axis and closing_axis must differ")
        for name in ("pad_size", "finger_size", "palm_size"):
            if any(not s > 0 for s in getattr(self, name)):
                raise ConfigError(f"gripper.geometry.{name} must be three positive full extents (m)")
        if not 0 < self.max_opening < 1.0:
            raise ConfigError(f"gripper.geometry.max_opening {self.max_opening} must be in (0, 1) m")
        if not self.finger_depth > 0:
            raise ConfigError("gripper.geometry.finger_depth must be positive (m)")


@dataclass(frozen=True)
class GripperConfig:
    """The gripper: one actuator commanded in ``command_range`` and its measured command -> width map.

    Attributes:
        actuator: actuator name; its ctrl is the command (e.g. 0 = open .. 255 = closed).
        joints: finger joint names (for reading the state).
        pad_geoms: the two pad collision geoms (contacts with them count as grasp contacts).
        command_range: [open command, closed command].
        command_to_width: pairs [command, gap between the pads (m)] measured in simulation with nothing
            between the pads; commands increasing, widths non-increasing.
        force: grip force limit (N) of the actuator (pad force).
        geometry: box model for grasp planning.
    """

    actuator: str
    joints: tuple[str, ...]
    pad_geoms: tuple[str, str]
    command_range: tuple[float, float]
    command_to_width: tuple[tuple[float, float], ...]
    force: float
    geometry: GripperGeometry

    def __post_init__(self) -> None:
        lo, hi = self.command_range
        if not lo < hi:
            raise ConfigError(f"gripper.command_range {list(self.command_range)} must be [open, closed], open < closed")
        if len(self.command_to_width) < 2:
            raise ConfigError("gripper.command_to_width needs at least two [command, width_m] pairs")
        cmds = np.array([c for c, _ in self.command_to_width])
        widths = np.array([w for _, w in self.command_to_width])
        if np.any(np.diff(cmds) <= 0):
            raise ConfigError("gripper.command_to_width commands must be strictly increasing")
        if np.any(np.diff(widths) > 0):
            raise ConfigError("gripper.command_to_width widths must not increase as the command increases")
        if cmds[0] < lo or cmds[-1] > hi:
            raise ConfigError(f"gripper.command_to_width commands must lie in command_range {list(self.command_range)}")
        if widths.min() < -1e-3 or widths.max() > self.geometry.max_opening + 1e-3:
            raise ConfigError("gripper.command_to_width widths must lie in "
                              f"[0, max_opening={self.geometry.max_opening}] m")
        if not self.force > 0:
            raise ConfigError("gripper.force must be positive (N)")

    def command_to_width_m(self, command: float) -> float:
        """Pad gap (m) the gripper settles at for ``command`` with nothing between the pads (interpolated)."""
        cmds = [c for c, _ in self.command_to_width]
        widths = [w for _, w in self.command_to_width]
        return float(np.interp(command, cmds, widths))

    def width_to_command(self, width_m: float) -> float:
        """Command whose free pad gap is ``width_m`` (m); clipped to the map's range."""
        cmds = np.array([c for c, _ in self.command_to_width])[::-1]
        widths = np.array([w for _, w in self.command_to_width])[::-1]  # increasing for np.interp
        return float(np.interp(width_m, widths, cmds))


@dataclass(frozen=True)
class RobotConfig:
    """A simulated (or third-party) robot: MJCF files plus the names and numbers the harness needs.

    Attributes:
        name: robot name (usually the folder name).
        mjcf: the robot MJCF (absolute after loading); attach it into scenes.
        scene: a standalone scene MJCF with floor and light (absolute after loading).
        arm: arm names, limits, home pose.
        gripper: gripper names, command map, geometry.
    """

    name: str
    mjcf: Path
    scene: Path
    arm: ArmConfig
    gripper: GripperConfig

    def command_to_width(self, command: float) -> float:
        """Pad gap (m) for a gripper command (see :meth:`GripperConfig.command_to_width_m`)."""
        return self.gripper.command_to_width_m(command)

    def width_to_command(self, width_m: float) -> float:
        """Gripper command for a pad gap (m) (see :meth:`GripperConfig.width_to_command`)."""
        return self.gripper.width_to_command(width_m)

    def missing_in(self, model: mujoco.MjModel) -> list[str]:
        """Descriptions of everything this config names that ``model`` lacks or contradicts."""
        problems: list[str] = []
        checks = [(mujoco.mjtObj.mjOBJ_JOINT, "joint", n) for n in (*self.arm.joints, *self.gripper.joints)]
        checks += [(mujoco.mjtObj.mjOBJ_ACTUATOR, "actuator", n) for n in (*self.arm.actuators, self.gripper.actuator)]
        checks += [(mujoco.mjtObj.mjOBJ_SITE, "site", n) for n in (self.arm.flange_site, self.arm.tcp_site)]
        checks += [(mujoco.mjtObj.mjOBJ_GEOM, "geom", n) for n in self.gripper.pad_geoms]
        for obj, kind, name in checks:
            if mujoco.mj_name2id(model, obj, name) < 0:
                problems.append(f"{kind} {name!r}")
        if problems:
            return problems
        for j, a in zip(self.arm.joints, self.arm.actuators, strict=True):
            act = model.actuator(a)
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            if act.trntype[0] != mujoco.mjtTrn.mjTRN_JOINT or act.trnid[0] != jid:
                problems.append(f"actuator {a!r} does not drive joint {j!r} (arm.actuators must follow arm.joints)")
        for j, (lo, hi) in zip(self.arm.joints, self.arm.position_limits, strict=True):
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            if model.jnt_limited[jid]:
                mlo, mhi = model.jnt_range[jid]
                if lo < mlo - 1e-9 or hi > mhi + 1e-9:
                    problems.append(f"joint {j!r} limits [{lo}, {hi}] exceed the MJCF range [{mlo}, {mhi}]")
        return problems

    def validate_against(self, model: mujoco.MjModel) -> None:
        """Raise SceneError listing every joint/actuator/site/geom this config names that ``model`` lacks."""
        problems = self.missing_in(model)
        if problems:
            raise SceneError(f"robot {self.name!r} does not match the compiled model: missing or inconsistent "
                             f"{', '.join(problems)}; fix the names in its robot.yaml or the MJCF")


def available_robots() -> list[str]:
    """Names of the robot folders under ``sim/robots`` that have a robot.yaml."""
    return sorted(p.parent.name for p in ROBOTS_DIR.glob(f"*/{ROBOT_YAML}"))


def robot_yaml_path(name_or_path: str | Path) -> Path:
    """The robot.yaml for a robot folder name under sim/robots, or a given YAML file / folder path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        if not p.is_file():
            raise ConfigError(f"robot config {p} does not exist; check the path")
        return p
    if p.is_dir() and (p / ROBOT_YAML).is_file():
        return p / ROBOT_YAML
    candidate = ROBOTS_DIR / str(name_or_path) / ROBOT_YAML
    if len(p.parts) == 1 and candidate.is_file():
        return candidate
    raise UnknownNameError("robot", str(name_or_path), available_robots())


def load_robot_config(name_or_path: str | Path, overrides: tuple[str, ...] | list[str] = (),
                      validate: bool = True) -> RobotConfig:
    """Load a :class:`RobotConfig` by robot folder name (e.g. ``"inovo_2f85"``) or YAML path.

    Unknown keys and missing fields raise ConfigError naming them; ``overrides`` are ``a.b=c`` strings.
    With ``validate`` the MJCF is compiled and :meth:`RobotConfig.validate_against` is applied (SceneError).
    """
    path = robot_yaml_path(name_or_path)
    data = load_yaml(path)
    for key in ("mjcf", "scene"):
        if isinstance(data.get(key), str) and not Path(data[key]).is_absolute():
            data[key] = str((path.parent / data[key]).resolve())
    cfg = from_dict(RobotConfig, data, overrides, where=str(path))
    for key in ("mjcf", "scene"):
        if not getattr(cfg, key).is_file():
            raise ConfigError(f"{path}: {key} file {getattr(cfg, key)} does not exist; paths are relative to the YAML")
    if validate:
        try:
            model = mujoco.MjModel.from_xml_path(str(cfg.mjcf))
        except ValueError as exc:
            raise SceneError(f"{path}: MJCF {cfg.mjcf} does not compile: {exc}") from exc
        cfg.validate_against(model)
    log.debug("loaded robot config %s from %s", cfg.name, path)
    return cfg
