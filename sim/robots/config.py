"""Robot configs: which MJCF(s), which joints/actuators/sites, limits and gripper geometry, from one YAML.

A robot folder ``sim/robots/<name>/`` holds a ``robot.yaml`` that names everything the harness needs
from its MJCF, so a third-party arm and gripper are plugged in with only a YAML (pass its path to
:func:`load_robot_config`). The robot is described either by one pre-combined ``mjcf`` or by an arm file
(``arm.mjcf``) and a gripper file (``gripper.mjcf``) that :mod:`sim.robots.compose` attaches at
``gripper.attach_site``; ``base_pose`` places the arm base in the world. Units: m, rad, s, kg, N. Frames:
world = the table frame (table top z = 0, z up); the arm base sits at ``base_pose`` in it (identity by
default, where world = robot base frame); the gripper geometry is given in the TCP frame (origin at the
pinch point midway between the pad centres, ``approach_axis`` pointing out of the flange towards the
fingertips, ``closing_axis`` along which the pads move).

Paths in the YAML (``mjcf``, ``scene``, ``arm.mjcf``, ``gripper.mjcf``) are relative to the YAML's folder and
are resolved to absolute paths on load. Names are those of the composed model: a gripper element is called
``gripper.prefix`` + its name in the gripper file; actuators left out (or null) are found from the joints they
drive. Every key, its
meaning and default: ``sim/robots/README.md``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import mujoco
import numpy as np

from sim.robots.force_map import ForceMap
from torm.config import from_dict, load_yaml
from torm.errors import ConfigError, SceneError, UnknownNameError

if TYPE_CHECKING:
    from sim.robots.ids import RobotIds

log = logging.getLogger(__name__)

ROBOTS_DIR = Path(__file__).resolve().parent  # one folder per robot beside this module
ROBOT_YAML = "robot.yaml"

Axis = Literal["x", "y", "z"]


@dataclass(frozen=True)
class BasePose:
    """Where the arm base sits in the world (table frame, m / rad).

    Attributes:
        position: (x, y, z) of the arm's base frame origin in the world (m).
        orientation: the base frame's orientation in the world: a unit quaternion ``[w, x, y, z]`` or
            ``[roll, pitch, yaw]`` (rad, rotations about the fixed world x, y, z axes in that order).
    """

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not np.all(np.isfinite(self.position)):
            raise ConfigError(f"base_pose.position must be three finite numbers (m), got {list(self.position)}")
        o = np.asarray(self.orientation, float)
        if o.shape not in ((3,), (4,)) or not np.all(np.isfinite(o)):
            raise ConfigError(f"base_pose.orientation must be a quaternion [w, x, y, z] or [roll, pitch, yaw] (rad), "
                              f"got {list(self.orientation)}")
        if o.shape == (4,) and np.linalg.norm(o) < 1e-9:
            raise ConfigError("base_pose.orientation quaternion has zero length; identity is [1, 0, 0, 0]")

    @property
    def quat(self) -> np.ndarray:
        """(4,) unit quaternion wxyz of the base in the world."""
        o = np.asarray(self.orientation, float)
        if o.shape == (4,):
            return o / np.linalg.norm(o)
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_euler("xyz", o).as_quat()
        return np.array([w, x, y, z])

    @property
    def T_world_base(self) -> np.ndarray:
        """(4, 4) pose of the arm base frame in the world."""
        T = np.eye(4)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, self.quat)
        T[:3, :3] = mat.reshape(3, 3)
        T[:3, 3] = self.position
        return T

    @property
    def is_identity(self) -> bool:
        return bool(np.allclose(self.position, 0.0) and np.allclose(np.abs(self.quat[0]), 1.0))


@dataclass(frozen=True)
class ArmConfig:
    """The arm: joint names, TCP and flange sites, limits and the home pose (+ its MJCF when separate).

    Attributes:
        joints: arm joint names in kinematic order (n).
        flange_site: site at the tool flange (gripper mounting face).
        tcp_site: site at the tool centre point (pinch point of the gripper); usually in the gripper file.
        position_limits: (n, 2) [lower, upper] joint limits (rad), within the MJCF joint ranges.
        velocity_limits: (n,) joint speed limits (rad/s).
        acceleration_limits: (n,) joint acceleration limits (rad/s^2).
        home: (n,) "ready" joint configuration (rad); None (left out) = solved on load: the TCP above the
            reconstruction box, pointing down (:func:`solve_home`; the value is logged).
        mjcf: the arm's own MJCF (absolute after loading) when the gripper comes from ``gripper.mjcf``;
            None with a pre-combined top-level ``mjcf``.
        actuators: position actuators driving ``joints``, same order (ctrl = joint target, rad); None (or a
            None entry) = the actuator whose transmission is that joint (for MJCFs with unnamed actuators).
    """

    joints: tuple[str, ...]
    flange_site: str
    tcp_site: str
    position_limits: tuple[tuple[float, float], ...]
    velocity_limits: tuple[float, ...]
    acceleration_limits: tuple[float, ...]
    home: tuple[float, ...] | None = None
    mjcf: Path | None = None
    actuators: tuple[str | None, ...] | None = None

    def __post_init__(self) -> None:
        n = len(self.joints)
        if n == 0:
            raise ConfigError("arm.joints is empty; list the arm's joint names in kinematic order")
        if len(set(self.joints)) != n:
            raise ConfigError(f"arm.joints has duplicates: {list(self.joints)}")
        names = ["position_limits", "velocity_limits", "acceleration_limits"]
        if self.home is not None:
            names.append("home")
        if self.actuators is not None:
            names.append("actuators")
        for name in names:
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
        outside = [j for j, q, (lo, hi) in zip(self.joints, self.home or (), self.position_limits, strict=False)
                   if not lo <= q <= hi]
        if outside:
            raise ConfigError(f"arm.home is outside arm.position_limits for joints {outside}")

    @property
    def actuator_names(self) -> tuple[str | None, ...]:
        """(n,) the named actuators per joint; None where it is found from the joint."""
        return tuple(self.actuators) if self.actuators is not None else (None,) * len(self.joints)

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
        if self.home is None:
            raise ConfigError("arm.home is not set and was not solved; load the robot with load_robot_config, which "
                              "solves it, or give arm.home in the YAML")
        return np.array(self.home)


@dataclass(frozen=True)
class GripperGeometry:
    """Box approximation of the gripper for grasp-planner collision checks, in the TCP frame (m).

    Sizes are full extents ``[x, y, z]`` of the TCP frame's axes. The pads sit at
    ``+-(opening / 2 + pad_size[closing] / 2)`` along ``closing_axis`` and centred on the TCP along
    ``approach_axis`` (for a gripper whose pads move along the approach as they close: centred where
    ``gripper.tcp_offset`` is 0); each finger box lies directly behind its pad (further from the TCP along the
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
        from dataclasses import asdict

        from torm.grasp.gripper import GripperGeometry as PlannerGeometry

        try:  # the grasp planner's rules (finger and palm boxes must agree), checked when the YAML loads
            PlannerGeometry.from_robot_config(asdict(self))
        except ConfigError as exc:
            raise ConfigError(f"gripper.{exc}") from exc


@dataclass(frozen=True)
class TcpSiteDeclaration:
    """A TCP site the gripper file lacks, added on composing (Menagerie hands often have none).

    Attributes:
        body: the body (name in the composed model, i.e. with ``gripper.prefix``) the site is fixed to.
        pos: (x, y, z) of the site in that body's frame (m).
        quat: (w, x, y, z) orientation of the site in that body's frame; its axes are the TCP frame's.
    """

    body: str
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not self.body:
            raise ConfigError("gripper.define_tcp.body is empty; name the body the TCP site is fixed to")
        if np.linalg.norm(self.quat) < 1e-9:
            raise ConfigError("gripper.define_tcp.quat has zero length; identity is [1, 0, 0, 0]")


@dataclass(frozen=True)
class GripperConfig:
    """The gripper: one actuator commanded in ``command_range``, its measured maps, and the planner's box model.

    Attributes:
        joints: finger joint names (state read-out; an unnamed actuator is found from them).
        pad_geoms: the pad collision geoms, ``[[left pads...], [right pads...]]`` (any number per finger), or
            ``[left, right]`` for one pad per finger. Contacts with them count as grasp contacts. An entry is a
            geom name, ``body:NAME`` (every collision geom of body NAME, for unnamed geoms) or ``body:NAME#K``
            (the K-th geom of body NAME, 0-based, in file order).
        command_range: ``[open command, closed command]``; either order (e.g. ``[255, 0]`` when 255 = open).
        command_to_width: pairs ``[command, gap between the pads (m)]`` measured in simulation with nothing
            between the pads; commands strictly increasing, the gap shrinking towards the closed command.
        geometry: box model for grasp planning.
        mjcf: the gripper's own MJCF (absolute after loading), attached to the arm at ``attach_site``; None with
            a pre-combined top-level ``mjcf``.
        attach_site: arm site the gripper's root body is attached at (default ``arm.flange_site``).
        prefix: prefix added to every gripper element's name on attaching (default ``gripper_``).
        root_body: the gripper body to attach (default: the only body directly in the gripper's worldbody).
        actuator: the actuator whose ctrl is the command; None = the actuator driving one of ``joints`` (directly
            or through a tendon).
        tcp_offset: pairs ``[gap (m), pad-centre position along the approach axis in the TCP frame (m)]``,
            gaps strictly increasing, measured with nothing between the pads (``measure_gripper --tcp-offset``);
            empty = the pads stay centred on the TCP at every width (a slide gripper).
        force: pad force (N) the MJCF's own actuator force limit gives (as authored; informational).
        force_map: measured pad force per actuator setting and width (``measure_gripper --force``); None = the
            actuator force limit is taken as the pad force, allowed only for a direct drive (the actuator moves
            slide joints, directly or through a tendon); a linkage (hinge) gripper without one is refused.
        define_tcp: a TCP site to add (named ``arm.tcp_site``) when the gripper file has none.
        servo_gain_scale: multiplies the gripper actuator's position-servo gains when the robot is composed
            (gain and the bias's constant and stiffness terms by it, the damping by its square root: the same
            damping ratio), for a hand whose MJCF servo squeezes far less than the real hand (MuJoCo Menagerie's
            Panda hand: about 25 N/m x gap per finger); 1 = as authored. Only for a position-servo actuator
            (``biastype="affine"`` with negative length feedback); re-measure ``force_map`` after changing it.
    """

    joints: tuple[str, ...]
    pad_geoms: tuple[str, str] | tuple[tuple[str, ...], tuple[str, ...]]
    command_range: tuple[float, float]
    command_to_width: tuple[tuple[float, float], ...]
    geometry: GripperGeometry
    mjcf: Path | None = None
    attach_site: str | None = None
    prefix: str = "gripper_"
    root_body: str | None = None
    actuator: str | None = None
    tcp_offset: tuple[tuple[float, float], ...] = ()
    force: float | None = None
    force_map: ForceMap | None = None
    define_tcp: TcpSiteDeclaration | None = None
    servo_gain_scale: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 < self.servo_gain_scale <= 1e4:
            raise ConfigError(f"gripper.servo_gain_scale must be in (0, 10000], got {self.servo_gain_scale} "
                              "(1 = the MJCF's own gains)")
        pads = self.pad_geoms
        if len(pads) != 2:
            raise ConfigError("gripper.pad_geoms must be [left, right] or [[left pads...], [right pads...]]")
        nested = tuple((p,) if isinstance(p, str) else tuple(p) for p in pads)
        if not all(nested) or set(nested[0]) & set(nested[1]):
            raise ConfigError(f"gripper.pad_geoms needs at least one pad per finger, none shared: {pads}")
        object.__setattr__(self, "pad_geoms", nested)
        o, c = self.command_range
        if o == c:
            raise ConfigError(f"gripper.command_range {list(self.command_range)} must be [open, closed] with "
                              "open != closed (open > closed is fine, e.g. [255, 0])")
        if len(self.command_to_width) < 2:
            raise ConfigError("gripper.command_to_width needs at least two [command, width_m] pairs")
        cmds = np.array([k for k, _ in self.command_to_width])
        widths = np.array([w for _, w in self.command_to_width])
        if np.any(np.diff(cmds) <= 0):
            raise ConfigError("gripper.command_to_width commands must be strictly increasing")
        shrink = np.diff(widths) * np.sign(c - o)  # gap change per step towards the closed command
        if np.any(shrink > 0):
            raise ConfigError("gripper.command_to_width widths must not grow as the command moves from open "
                              f"({o}) towards closed ({c})")
        lo, hi = sorted(self.command_range)
        if cmds[0] < lo or cmds[-1] > hi:
            raise ConfigError(f"gripper.command_to_width commands must lie in command_range {list(self.command_range)}")
        if widths.min() < -1e-3 or widths.max() > self.geometry.max_opening + 1e-3:
            raise ConfigError("gripper.command_to_width widths must lie in "
                              f"[0, max_opening={self.geometry.max_opening}] m")
        if self.tcp_offset:
            tw = np.array([w for w, _ in self.tcp_offset])
            if np.any(np.diff(tw) <= 0) or tw.min() < -1e-3 or tw.max() > self.geometry.max_opening + 1e-3:
                raise ConfigError("gripper.tcp_offset gaps must be strictly increasing and lie in "
                                  f"[0, max_opening={self.geometry.max_opening}] m")
            if max(abs(off) for _, off in self.tcp_offset) > 0.2:
                raise ConfigError("gripper.tcp_offset offsets must be under 0.2 m; they are metres, not mm")
        if self.force is not None and not self.force > 0:
            raise ConfigError("gripper.force must be positive (N)")

    @property
    def left_pads(self) -> tuple[str, ...]:
        return self.pad_geoms[0]  # type: ignore[return-value]

    @property
    def right_pads(self) -> tuple[str, ...]:
        return self.pad_geoms[1]  # type: ignore[return-value]

    @property
    def open_command(self) -> float:
        return float(self.command_range[0])

    @property
    def closed_command(self) -> float:
        return float(self.command_range[1])

    def command_to_width_m(self, command: float) -> float:
        """Pad gap (m) the gripper settles at for ``command`` with nothing between the pads (interpolated)."""
        cmds = [k for k, _ in self.command_to_width]
        widths = [w for _, w in self.command_to_width]
        return float(np.interp(command, cmds, widths))

    def width_to_command(self, width_m: float) -> float:
        """Command whose free pad gap is ``width_m`` (m); clipped to the map's range."""
        cmds = np.array([k for k, _ in self.command_to_width])
        widths = np.array([w for _, w in self.command_to_width])
        order = np.argsort(widths, kind="stable")  # np.interp needs increasing widths
        return float(np.interp(width_m, widths[order], cmds[order]))

    def tcp_offset_m(self, width_m: float) -> float:
        """Pad-centre position along the approach axis in the TCP frame (m) at pad gap ``width_m`` (m); 0 without
        a table."""
        if not self.tcp_offset:
            return 0.0
        return float(np.interp(width_m, [w for w, _ in self.tcp_offset], [o for _, o in self.tcp_offset]))


@dataclass(frozen=True)
class RobotConfig:
    """A simulated (or third-party) robot: MJCF file(s) plus the names and numbers the harness needs.

    Attributes:
        name: robot name (usually the folder name).
        arm: arm names, limits, home pose (and ``arm.mjcf`` for a separate arm file).
        gripper: gripper names, command maps, geometry (and ``gripper.mjcf`` for a separate gripper file).
        mjcf: a pre-combined arm + gripper MJCF (absolute after loading); None when ``arm.mjcf`` and
            ``gripper.mjcf`` are given.
        scene: an optional standalone scene MJCF (floor, light) for viewing the robot; the harness never needs it.
        base_pose: where the arm base sits in the world (default: the world origin).
        gravcomp: True = gravity compensation on every robot body, False = none, None = as the MJCF says.
        reach_min_share: the simulated backend refuses the robot when it reaches less than this share of the
            workspace box with the gripper pointing down (:mod:`sim.robots.reach`); lower it for an arm meant to
            cover part of the box.
    """

    name: str
    arm: ArmConfig
    gripper: GripperConfig
    mjcf: Path | None = None
    scene: Path | None = None
    base_pose: BasePose = field(default_factory=BasePose)
    gravcomp: bool | None = None
    reach_min_share: float = 0.75

    def __post_init__(self) -> None:
        if not 0.0 <= self.reach_min_share <= 1.0:
            raise ConfigError(f"robot {self.name!r}: reach_min_share must be in [0, 1], got {self.reach_min_share}")
        separate = (self.arm.mjcf is not None, self.gripper.mjcf is not None)
        if self.mjcf is not None and any(separate):
            raise ConfigError(f"robot {self.name!r}: give either a pre-combined mjcf or arm.mjcf + gripper.mjcf, "
                              "not both")
        if self.mjcf is None and not all(separate):
            missing = [k for k, v in zip(("arm.mjcf", "gripper.mjcf"), separate, strict=True) if not v]
            raise ConfigError(f"robot {self.name!r}: no mjcf and no {' / '.join(missing)}; give a pre-combined mjcf "
                              "or both arm.mjcf and gripper.mjcf")

    @property
    def composed(self) -> bool:
        """Whether the robot is composed from a separate arm and gripper file."""
        return self.mjcf is None

    @property
    def attach_site(self) -> str:
        """The arm site the gripper is attached at."""
        return self.gripper.attach_site or self.arm.flange_site

    def files(self) -> tuple[Path, ...]:
        """The MJCF files this robot is built from."""
        return (self.mjcf,) if self.mjcf is not None else (self.arm.mjcf, self.gripper.mjcf)  # type: ignore[return-value]

    def command_to_width(self, command: float) -> float:
        """Pad gap (m) for a gripper command (see :meth:`GripperConfig.command_to_width_m`)."""
        return self.gripper.command_to_width_m(command)

    def width_to_command(self, width_m: float) -> float:
        """Gripper command for a pad gap (m) (see :meth:`GripperConfig.width_to_command`)."""
        return self.gripper.width_to_command(width_m)

    def robot_spec(self) -> mujoco.MjSpec:
        """A fresh MjSpec of the robot alone, composed and placed at ``base_pose`` (see :mod:`sim.robots.compose`)."""
        from sim.robots.compose import robot_spec

        return robot_spec(self)

    def robot_model(self) -> mujoco.MjModel:
        """The compiled robot-only model (base at ``base_pose``): for IK, FK and plan-time collision checks."""
        from sim.robots.compose import compile_spec

        return compile_spec(self.robot_spec(), f"robot {self.name!r}")

    def resolve(self, model: mujoco.MjModel) -> RobotIds:
        """Ids of every joint/actuator/site/geom this config names in ``model`` (SceneError listing what is missing)."""
        from sim.robots.ids import RobotIds

        return RobotIds.resolve(model, self)

    def missing_in(self, model: mujoco.MjModel) -> list[str]:
        """Descriptions of everything this config names that ``model`` lacks or contradicts."""
        from sim.robots.ids import problems_in

        return problems_in(model, self)

    def validate_against(self, model: mujoco.MjModel, require_force_map: bool = True) -> None:
        """Raise SceneError listing every joint/actuator/site/geom this config names that ``model`` lacks, or (with
        ``require_force_map``) when a linkage gripper has no ``gripper.force_map``."""
        problems = self.missing_in(model)
        if problems:
            raise SceneError(f"robot {self.name!r} does not match the compiled model: missing or inconsistent "
                             f"{', '.join(problems)}; fix the names in its robot.yaml or the MJCF")
        if require_force_map:
            from sim.robots.ids import force_map_problem

            why = force_map_problem(model, self, self.resolve(model))
            if why:
                raise SceneError(why)


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


_PATH_KEYS = ((), "mjcf"), ((), "scene"), (("arm",), "mjcf"), (("gripper",), "mjcf")


def _resolve_paths(data: dict, folder: Path) -> None:
    for parents, key in _PATH_KEYS:
        d = data
        for k in parents:
            d = d.get(k) if isinstance(d, dict) else None
        if isinstance(d, dict) and isinstance(d.get(key), str) and not Path(d[key]).is_absolute():
            d[key] = str((folder / d[key]).resolve())


def load_robot_config(name_or_path: str | Path, overrides: tuple[str, ...] | list[str] = (),
                      validate: bool = True, require_force_map: bool = True) -> RobotConfig:
    """Load a :class:`RobotConfig` by robot folder name (e.g. ``"inovo_2f85"``) or YAML path.

    Unknown keys and missing fields raise ConfigError naming them; ``overrides`` are ``a.b=c`` strings.
    With ``validate`` the robot is composed and compiled and :meth:`RobotConfig.validate_against` is applied
    (SceneError; ``require_force_map=False`` lets a linkage gripper without a force map load, for measuring one).
    Without ``arm.home`` the home pose is solved (:func:`solve_home`).
    """
    path = robot_yaml_path(name_or_path)
    data = load_yaml(path)
    _resolve_paths(data, path.parent)
    cfg = from_dict(RobotConfig, data, overrides, where=str(path))
    files = {"mjcf": cfg.mjcf, "scene": cfg.scene, "arm.mjcf": cfg.arm.mjcf, "gripper.mjcf": cfg.gripper.mjcf}
    for key, f in files.items():
        if f is not None and not f.is_file():
            raise ConfigError(f"{path}: {key} file {f} does not exist; paths are relative to the YAML")
    if validate or cfg.arm.home is None:
        model = cfg.robot_model()
        cfg.validate_against(model, require_force_map)
        if cfg.arm.home is None:
            from dataclasses import replace

            home = solve_home(cfg, model)
            log.warning("robot %s: arm.home is not set; solved it (TCP above the workspace box, pointing down): "
                        "home: %s (put it in %s to keep it)", cfg.name, [round(float(v), 4) for v in home],
                        path)
            cfg = replace(cfg, arm=replace(cfg.arm, home=tuple(float(v) for v in home)))
    log.debug("loaded robot config %s from %s", cfg.name, path)
    return cfg


def solve_home(rcfg: RobotConfig, model: mujoco.MjModel | None = None,
               heights_m: tuple[float, ...] = (0.30, 0.20, 0.12)) -> np.ndarray:
    """A home pose for a robot without ``arm.home``: the TCP above the reconstruction box
    (:data:`sim.workspace.WORKSPACE_BOUNDS`) pointing down, closing axis along world y, solved with execution's IK
    (:meth:`torm.execution.ik.IKSolver.solve_free`) from the middle of the joint limits. Tried in order: above the
    box centre, then halfway to the box point nearest the base, each at ``heights_m`` (m above the table); the
    first reachable one wins (a small arm gets a lower, nearer home).

    Returns:
        (n,) joint angles (rad). Raises SceneError when none is reachable (the base cannot reach the box).
    """
    from sim.robots.reach import _down_rotation
    from sim.workspace import WORKSPACE_BOUNDS
    from torm.execution.ik import IKSolver

    model = model if model is not None else rcfg.robot_model()
    ik = IKSolver(model, tuple(rcfg.arm.joints), rcfg.arm.tcp_site)
    g = rcfg.gripper.geometry
    lo, hi = WORKSPACE_BOUNDS[0][:2], WORKSPACE_BOUNDS[1][:2]
    centre = 0.5 * (lo + hi)
    near = np.clip(np.asarray(rcfg.base_pose.position[:2], float), lo, hi)
    mid = 0.5 * (rcfg.arm.lower + rcfg.arm.upper)
    T = np.eye(4)
    T[:3, :3] = _down_rotation(g.approach_axis, g.closing_axis, np.array([0.0, 1.0, 0.0]))
    best = None
    for xy in (centre, 0.5 * (centre + near)):
        for h in heights_m:
            T[:3, 3] = [xy[0], xy[1], h]
            res = ik.solve_free(T, mid, restarts=16)
            if res.converged:
                return res.q
            best = res if best is None or res.pos_err < best.pos_err else best
    raise SceneError(f"robot {rcfg.name!r}: arm.home is not set and no joint pose puts the TCP above the workspace "
                     f"box {np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()} pointing down at heights "
                     f"{list(heights_m)} m (best residual {best.pos_err * 1000:.0f} mm); set arm.home in the YAML or "
                     "move base_pose closer to the box")
