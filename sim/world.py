"""Build a MuJoCo world for a scenario: table, floor, lights, the robot at its base pose, settled objects.

Frames and units: world = the table frame, z up, metres, radians, seconds, kilograms; the table top
surface is z = 0. The robot's arm base sits at its robot.yaml ``base_pose`` (the world origin by default,
where world = robot base frame). Geom groups (CONTEXT conventions): 0 environment visuals (the table geom
also collides), 1 robot visuals, 2 glass object visuals, 3 collision geoms, 4 opaque object visuals. Robot
geoms are moved into group 1 (or kept in 3 when they collide and sit there) whatever group their MJCF uses,
so the capture rig, which hides groups 1 and 3, never sees the robot.

The robot (:func:`sim.robots.compose.robot_spec`) is the base spec the scene is added to, so it keeps its
own ``<compiler>`` (angle units: add world elements with quaternions, never euler or joint ranges) and its
own ``<option>`` (integrator, timestep, solver...); the scene only adds the glass-holding contact settings
(elliptic cone, impratio 10, multiccd) where the robot leaves MuJoCo's defaults.

Objects are free bodies ``obj<k>_<name>`` (k = 1-based position in the scenario's object list = the
instance id in masks). Each has one visual mesh geom ``obj<k>_<name>_visual`` (contype/conaffinity
0) and collision geoms ``obj<k>_<name>_col<i>`` (group 3). The body frame is the library object
frame (lowest point at z = 0, footprint centred), with mass and inertia set explicitly from the mesh. A
scenario's fixture (rack, tray) is a static body ``fixture_<name>`` of opaque box geoms in group 0 (rendered,
colliding, never in masks).

:func:`build_world` samples a layout from ``seed``, builds the model with MjSpec, lets the objects
settle under gravity, verifies the result (nothing tipped, slid or fell off, no interpenetration, no
MuJoCo warnings) and re-samples the layout when the check fails. The settled state is what
:meth:`World.reset` restores.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import trimesh

from sim.scenes.fixtures import PlacedFixture, get_fixture, pose_matrix
from sim.scenes.objects import ObjectAsset, get_object
from sim.scenes.placement import Placement, PlacementConfig, place_scene
from sim.scenes.scenario import Scenario, get_scenario
from sim.workspace import TABLE_HEIGHT, WORKSPACE_BOUNDS  # noqa: F401  (re-exported: defined here before)
from torm.errors import ConfigError, SceneError
from torm.types import TriMesh

if TYPE_CHECKING:
    from sim.realism import RealismRecord
    from sim.robots.config import RobotConfig
    from sim.robots.ids import RobotIds

log = logging.getLogger(__name__)

FLOOR_Z = -0.75  # floor below the table top (m)
TABLE_X = (-0.45, 1.25)  # table top extent (m); the robot base at the origin sits on it
TABLE_Y = (-0.90, 0.90)
TABLE_THICKNESS = 0.04

GROUP_ENV, GROUP_ROBOT, GROUP_GLASS, GROUP_COLLISION, GROUP_OPAQUE = 0, 1, 2, 3, 4
GLASS_RGBA = (0.86, 0.93, 0.96, 0.3)
CERAMIC_RGBA = (0.93, 0.92, 0.88, 1.0)
OBJECT_FRICTION = (0.5, 0.005, 0.0001)  # glass on wood/glass (sliding, torsional, rolling)


@dataclass(frozen=True)
class WorldConfig:
    """Build/settle parameters (s, m, deg). The defaults suit every scenario of the shipped suites."""

    settle_time: float = 0.6  # physics time to let the objects come to rest (s)
    drop_height: float = 0.0005  # objects start this far above the table (m)
    max_settle_shift: float = 0.004  # allowed xy slide while settling (m)
    max_settle_tilt_deg: float = 3.0  # allowed tilt of the object's z axis while settling (deg)
    max_fixture_tilt_deg: float = 6.0  # the same for objects standing in a fixture (a tube leaning in its hole)
    max_penetration: float = 0.002  # deepest allowed contact penetration after settling (m)
    max_resamples: int = 20  # layouts to try before giving up
    timestep: float | None = None  # s; None = the robot's own <option timestep> (0.002 s without a robot)

    def __post_init__(self) -> None:
        if not self.settle_time > 0:
            raise ConfigError(f"WorldConfig.settle_time must be positive, got {self.settle_time}")
        if self.timestep is not None and not self.timestep > 0:
            raise ConfigError(f"WorldConfig.timestep must be positive or None (the robot's own), got {self.timestep}")
        for name in ("drop_height", "max_settle_shift", "max_settle_tilt_deg", "max_fixture_tilt_deg",
                     "max_penetration"):
            if getattr(self, name) < 0:
                raise ConfigError(f"WorldConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.max_resamples < 1:
            raise ConfigError(f"WorldConfig.max_resamples must be >= 1, got {self.max_resamples}")


@dataclass(eq=False)
class WorldObject:
    """One object instance in a built world.

    Attributes:
        instance_id: k, 1-based position in the scenario object list (= mask value).
        name: library object name (e.g. "cup").
        body_name: MuJoCo body name ``obj<k>_<name>``.
        body_id: MuJoCo body id.
        visual_geom_ids: ids of the rendered geoms (group 2 glass or 4 opaque).
        collision_geom_ids: ids of the collision geoms (group 3).
        mass: kg.
        transparent: True for glass.
        mesh: the object's trimesh in its body frame (m).
        placement: the sampled table pose (x, y, yaw) before settling.
    """

    instance_id: int
    name: str
    body_name: str
    body_id: int
    visual_geom_ids: tuple[int, ...]
    collision_geom_ids: tuple[int, ...]
    mass: float
    transparent: bool
    mesh: trimesh.Trimesh
    placement: Placement
    _world: World | None = field(default=None, repr=False)

    @property
    def T_world_obj(self) -> np.ndarray:
        """(4, 4) current pose of the body frame in the world (from ``data.qpos``)."""
        if self._world is None:
            raise SceneError(f"object {self.body_name} is not attached to a world")
        return self._world.object_pose(self.instance_id)


@dataclass(eq=False)
class World:
    """A built, settled scene. ``data`` is live; :meth:`reset` restores the settled state.

    Attributes:
        model, data, spec: MuJoCo model, data and the MjSpec they were compiled from.
        scenario: scenario name; ``scenario_spec`` the full :class:`Scenario`.
        seed: the layout seed.
        objects: one :class:`WorldObject` per scenario object, ordered by instance id.
        table_height: z of the table top (m), 0.0.
        workspace_bounds: (2, 3) reconstruction box [[x, y, z]_min, [x, y, z]_max] (m).
        geom_to_instance: (ngeom,) int32, geom id -> instance id k (0 for non-object geoms).
        robot: robot name or None; ``robot_config`` its RobotConfig (None without a robot).
        robot_ids: the robot's joint/actuator/site/pad ids in ``model`` (None without a robot).
        robot_geom_ids: (R,) ids of every robot geom (all in group 1 or 3).
        layout_attempts: layouts sampled until one settled cleanly (1 = first try).
        realism: the realism record applied to the physics (None: the world as built, i.e. ideal).
        fixture: the scenario's fixture and its pose (None without one).
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    spec: mujoco.MjSpec
    scenario: str
    scenario_spec: Scenario
    seed: int
    objects: tuple[WorldObject, ...]
    geom_to_instance: np.ndarray
    robot: str | None = None
    robot_config: RobotConfig | None = None
    robot_ids: RobotIds | None = None
    robot_geom_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    layout_attempts: int = 1
    realism: RealismRecord | None = None
    fixture: PlacedFixture | None = None
    table_height: float = TABLE_HEIGHT
    workspace_bounds: np.ndarray = field(default_factory=lambda: WORKSPACE_BOUNDS.copy())
    _settled: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def _obj(self, k: int) -> WorldObject:
        if not 1 <= k <= len(self.objects):
            raise SceneError(f"instance id {k} is out of range; this world has objects 1..{len(self.objects)}")
        return self.objects[k - 1]

    def object_pose(self, k: int) -> np.ndarray:
        """(4, 4) current ``T_world_obj`` of instance ``k`` (1-based), read from the free joint in ``data.qpos``."""
        o = self._obj(k)
        adr = self.model.jnt_qposadr[self.model.body_jntadr[o.body_id]]
        q = self.data.qpos[adr:adr + 7]
        T = np.eye(4)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, q[3:7])
        T[:3, :3] = mat.reshape(3, 3)
        T[:3, 3] = q[:3]
        return T

    def object_meshes_world(self) -> list[trimesh.Trimesh]:
        """Each object's mesh in the world frame at its current pose (instance order), e.g. for GT metrics."""
        return [o.mesh.copy().apply_transform(self.object_pose(o.instance_id)) for o in self.objects]

    def object_outer_surfaces(self) -> dict[int, TriMesh]:
        """Instance id -> the object's outer surface in the world frame at its current pose (m).

        Sealed inner cavities (the closed toothpick box's inside: a shell with negative volume) are dropped,
        since no camera or finger can reach them; an open cup's inside is part of its outer surface.
        """
        out: dict[int, TriMesh] = {}
        for o, mesh in zip(self.objects, self.object_meshes_world(), strict=True):
            parts = [p for p in mesh.split(only_watertight=False) if p.volume > 0] if mesh.body_count > 1 else [mesh]
            outer = parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)
            out[o.instance_id] = TriMesh(np.asarray(outer.vertices), np.asarray(outer.faces))
        return out

    def reset(self) -> None:
        """Restore the settled state (qpos, zero velocities, robot controls at home) and run mj_forward."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._settled["qpos"]
        self.data.qvel[:] = 0.0
        self.data.ctrl[:] = self._settled["ctrl"]
        if self.model.na:
            self.data.act[:] = self._settled["act"]
        mujoco.mj_forward(self.model, self.data)


# ------------------------------------------------------------------------------------------------ build
def _yaw_quat(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2.0)), 0.0, 0.0, float(np.sin(yaw / 2.0))]


def _enable_multiccd(spec: mujoco.MjSpec) -> None:
    """Multi-point convex contacts (needed to hold glass): an enable flag in older MuJoCo, default-on since 3.x."""
    if hasattr(mujoco.mjtEnableBit, "mjENBL_MULTICCD"):
        spec.option.enableflags |= int(mujoco.mjtEnableBit.mjENBL_MULTICCD)
    if hasattr(mujoco.mjtDisableBit, "mjDSBL_MULTICCD"):
        spec.option.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_MULTICCD)


def physics_options(spec: mujoco.MjSpec, cfg: WorldConfig | None = None, robot: bool = True) -> None:
    """The timestep and the glass-holding contact settings, where the robot's own option leaves the default."""
    cfg = cfg or WorldConfig()
    default = mujoco.MjSpec().option
    if cfg.timestep is not None or not robot:
        spec.option.timestep = cfg.timestep or 0.002
    if spec.option.cone == default.cone:
        spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    if spec.option.impratio == default.impratio:
        spec.option.impratio = 10.0
    _enable_multiccd(spec)
    if spec.compiler.discardvisual:
        log.warning("the robot MJCF sets compiler discardvisual; turned off so the cameras see the objects")
        spec.compiler.discardvisual = False
    if spec.compiler.settotalmass > 0:
        log.warning("the robot MJCF sets compiler settotalmass, which would rescale the objects' masses too; "
                    "ignored (the robot keeps its authored masses)")
        spec.compiler.settotalmass = -1.0


def _setup_scene(spec: mujoco.MjSpec, cfg: WorldConfig, robot: bool = False) -> None:
    """Options, visuals, materials, floor, table and lights (m; orientations as quaternions / directions only,
    since the spec's angle unit is the robot's)."""
    spec.modelname = "torm_world"
    if not robot:
        spec.compiler.degree = False
    physics_options(spec, cfg, robot)
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 720
    spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
    spec.visual.headlight.diffuse = [0.4, 0.4, 0.4]
    spec.visual.headlight.specular = [0.2, 0.2, 0.2]
    spec.stat.center = [0.55, 0.0, 0.0]
    spec.stat.extent = 1.0

    spec.add_texture(name="table_tex", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.62, 0.52, 0.40], rgb2=[0.50, 0.41, 0.31], width=512, height=512,
                     mark=mujoco.mjtMark.mjMARK_EDGE, markrgb=[0.35, 0.30, 0.24])
    table_mat = spec.add_material(name="table_mat", rgba=[1, 1, 1, 1], texrepeat=[17, 18], texuniform=False,
                                  specular=0.2, shininess=0.2, reflectance=0.0)
    table_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "table_tex"
    spec.add_texture(name="floor_tex", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.30, 0.32, 0.35], rgb2=[0.24, 0.26, 0.28], width=256, height=256)
    floor_mat = spec.add_material(name="floor_mat", texrepeat=[8, 8], texuniform=True, reflectance=0.0)
    floor_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "floor_tex"
    spec.add_material(name="glass_mat", rgba=list(GLASS_RGBA), specular=1.0, shininess=1.0, reflectance=0.15)
    spec.add_material(name="ceramic_mat", rgba=list(CERAMIC_RGBA), specular=0.4, shininess=0.5, reflectance=0.0)
    spec.add_material(name="leg_mat", rgba=[0.35, 0.35, 0.37, 1], specular=0.3)
    spec.add_material(name="fixture_mat", rgba=[0.82, 0.84, 0.86, 1], specular=0.2, shininess=0.3)

    wb = spec.worldbody
    wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], pos=[0, 0, FLOOR_Z],
                material="floor_mat", group=GROUP_ENV)
    half = [(TABLE_X[1] - TABLE_X[0]) / 2, (TABLE_Y[1] - TABLE_Y[0]) / 2, TABLE_THICKNESS / 2]
    centre = [(TABLE_X[0] + TABLE_X[1]) / 2, (TABLE_Y[0] + TABLE_Y[1]) / 2, TABLE_HEIGHT - TABLE_THICKNESS / 2]
    # the table top both renders (group 0) and collides; objects and the robot stand on it
    wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=half, pos=centre, material="table_mat",
                group=GROUP_ENV, friction=[0.6, 0.005, 0.0001])
    leg_h = (TABLE_HEIGHT - TABLE_THICKNESS - FLOOR_Z) / 2
    for i, (sx, sy) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)]):
        wb.add_geom(name=f"table_leg{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.03, leg_h],
                    pos=[centre[0] + sx * (half[0] - 0.06), sy * (half[1] - 0.06), FLOOR_Z + leg_h],
                    material="leg_mat", group=GROUP_ENV, contype=0, conaffinity=0)
    wb.add_light(name="key_light", pos=[0.9, -0.6, 1.6], dir=[-0.35, 0.4, -1.0], diffuse=[0.55, 0.55, 0.55],
                 specular=[0.4, 0.4, 0.4], castshadow=True, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    wb.add_light(name="fill_light", pos=[0.2, 0.8, 1.4], dir=[0.3, -0.6, -1.0], diffuse=[0.3, 0.3, 0.3],
                 specular=[0.2, 0.2, 0.2], castshadow=False, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)


def _add_object_assets(spec: mujoco.MjSpec, assets: list[ObjectAsset]) -> None:
    """Add each distinct shape's visual mesh and collision hull meshes once."""
    done: set[str] = set()
    for a in assets:
        if a.shape in done:
            continue
        done.add(a.shape)
        spec.add_mesh(name=f"{a.shape}_visual", uservert=a.mesh.vertices.ravel().tolist(),
                      userface=a.mesh.faces.ravel().tolist())
        for i, h in enumerate(a.collision_hulls()):
            spec.add_mesh(name=f"{a.shape}_hull{i}", uservert=h.vertices.ravel().tolist(),
                          userface=h.faces.ravel().tolist())


def _add_fixture(spec: mujoco.MjSpec, name: str, pose: Placement) -> PlacedFixture:
    """A static body of opaque box geoms (group 0: rendered and colliding, never in masks) on the table top."""
    fx = get_fixture(name)
    body = spec.worldbody.add_body(name=f"fixture_{name}", pos=[pose.x, pose.y, TABLE_HEIGHT], quat=_yaw_quat(pose.yaw))
    for i, (c, h) in enumerate(fx.boxes):
        body.add_geom(name=f"fixture_{name}_box{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(h), pos=list(c),
                      material="fixture_mat", group=GROUP_ENV, friction=list(OBJECT_FRICTION))
    T = pose_matrix(pose.x, pose.y, pose.yaw)
    T[2, 3] = TABLE_HEIGHT
    return PlacedFixture(fx, T)


def _add_object(spec: mujoco.MjSpec, k: int, a: ObjectAsset, pose: Placement, drop: float) -> None:
    body = spec.worldbody.add_body(name=f"obj{k}_{a.name}", pos=[pose.x, pose.y, TABLE_HEIGHT + pose.z + drop],
                                   quat=_yaw_quat(pose.yaw))
    body.add_freejoint(name=f"obj{k}_{a.name}_free")
    I = a.inertia_3x3
    body.explicitinertial = True
    body.mass = a.mass
    body.ipos = a.com.tolist()
    body.fullinertia = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
    body.add_geom(name=f"obj{k}_{a.name}_visual", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{a.shape}_visual",
                  material="glass_mat" if a.transparent else "ceramic_mat",
                  group=GROUP_GLASS if a.transparent else GROUP_OPAQUE, contype=0, conaffinity=0, density=0.0)
    common = dict(group=GROUP_COLLISION, friction=list(OBJECT_FRICTION), density=0.0, rgba=[0.9, 0.4, 0.2, 0.5])
    if a.collision == "sphere":
        r = float(a.mesh.bounds[1, 2] / 2.0)
        # condim 6 enables the rolling friction: without it a released ball rolls on forever.
        body.add_geom(name=f"obj{k}_{a.name}_col0", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r, 0, 0],
                      pos=[0, 0, r], condim=6, **common)
    else:
        for i in range(len(a.collision_hulls())):
            body.add_geom(name=f"obj{k}_{a.name}_col{i}", type=mujoco.mjtGeom.mjGEOM_MESH,
                          meshname=f"{a.shape}_hull{i}", **common)


def hide_robot_geoms(spec: mujoco.MjSpec) -> list:
    """Put every geom of a robot spec in group 1 (robot visuals), except colliding geoms already in group 3.

    Returns the geom elements (their ``.id`` is the model geom id after compiling).
    """
    geoms = list(spec.geoms)
    for g in geoms:
        collides = bool(g.contype or g.conaffinity)
        if not (collides and g.group == GROUP_COLLISION):
            g.group = GROUP_ROBOT
    return geoms


def _new_spec(robot: str | Path | RobotConfig | None):
    """A fresh spec holding the robot at its base pose (names unprefixed) when ``robot`` is given.

    The composed robot spec is the base spec the scene is added to (not ``attach``-ed with an empty prefix), so
    joint/actuator/site names stay exactly as in its robot.yaml and its compiler and options stay its own.
    Returns (spec, RobotConfig or None, robot geom elements).
    """
    if robot is None:
        return mujoco.MjSpec(), None, []
    try:
        from sim.robots.config import RobotConfig, load_robot_config
    except ImportError as exc:  # pragma: no cover - depends on the robot package being present
        raise SceneError(f"robot {robot!r} requested but sim.robots.config is unavailable ({exc}); "
                         "pass robot=None for an object-only scene") from exc
    rcfg = robot if isinstance(robot, RobotConfig) else load_robot_config(robot, validate=False)
    spec = rcfg.robot_spec()
    return spec, rcfg, hide_robot_geoms(spec)


def _set_robot_home(data: mujoco.MjData, rcfg: RobotConfig, ids: RobotIds) -> None:
    data.qpos[ids.arm_qadr] = rcfg.arm.home_q
    data.ctrl[ids.arm_actuators] = rcfg.arm.home_q
    data.ctrl[ids.gripper_actuator] = rcfg.gripper.open_command


def _warnings(data: mujoco.MjData) -> dict[str, int]:
    return {mujoco.mjtWarning(i).name: int(w.number) for i, w in enumerate(data.warning) if w.number > 0}


def _tilt_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))


def _settle_problems(world: World, poses0: list[np.ndarray], cfg: WorldConfig) -> list[str]:
    """Reasons the settled state is unacceptable (empty list = fine)."""
    problems = []
    d = world.data
    warn = _warnings(d)
    if warn:
        problems.append(f"MuJoCo warnings {warn}")
    ws = world.workspace_bounds
    for o, T0 in zip(world.objects, poses0, strict=True):
        T = o.T_world_obj
        shift = float(np.linalg.norm(T[:2, 3] - T0[:2, 3]))
        tilt = _tilt_deg(T)
        if not np.all(np.isfinite(T)):
            problems.append(f"object {o.instance_id} ({o.name}) state is not finite")
        elif T[2, 3] < TABLE_HEIGHT - 0.01 or not (ws[0, 0] <= T[0, 3] <= ws[1, 0] and ws[0, 1] <= T[1, 3] <= ws[1, 1]):
            problems.append(f"object {o.instance_id} ({o.name}) left the table/workspace (at {T[:3, 3].round(3)})")
        elif shift > cfg.max_settle_shift or tilt > (cfg.max_fixture_tilt_deg if o.placement.z > 0
                                                     else cfg.max_settle_tilt_deg):
            problems.append(f"object {o.instance_id} ({o.name}) moved {shift * 1e3:.1f} mm / tilted {tilt:.1f} deg")
    g2i = world.geom_to_instance
    for c in d.contact[: d.ncon]:
        k1, k2 = int(g2i[c.geom1]), int(g2i[c.geom2])
        if k1 and k2 and k1 != k2:
            problems.append(f"objects {k1} and {k2} touch")
        if (k1 or k2) and c.dist < -cfg.max_penetration:
            problems.append(f"object {k1 or k2} penetrates by {-c.dist * 1e3:.1f} mm")
    return problems


def _compile(spec: mujoco.MjSpec, where: str) -> tuple[mujoco.MjModel, mujoco.MjData]:
    try:
        model = spec.compile()
    except ValueError as exc:
        raise SceneError(f"{where}: the scene does not compile: {exc}") from exc
    return model, mujoco.MjData(model)


def build_world(
    scenario: str | Scenario,
    seed: int = 0,
    robot: str | Path | RobotConfig | None = "inovo_2f85",
    *,
    config: WorldConfig | None = None,
    placement: PlacementConfig | None = None,
    realism: RealismRecord | None = None,
) -> World:
    """Build, settle and verify the scene for ``scenario`` with the layout drawn from ``seed``.

    Args:
        scenario: scenario name (see ``sim.scenes.scenario.list_scenarios()``) or a Scenario.
        seed: layout seed (x, y, yaw of every object); the same seed gives the same world.
        robot: robot folder name / robot.yaml path / loaded RobotConfig (placed at its ``base_pose``), or None.
        config: build and settle parameters.
        placement: placement parameters (gap rules, workspace rectangle).
        realism: contact and mass values to apply before settling (:func:`sim.realism.apply_physics`);
            None keeps the as-built (ideal) physics.

    Raises:
        SceneError: when no layout settles cleanly within ``config.max_resamples`` layouts.
    """
    cfg = config or WorldConfig()
    sc = get_scenario(scenario)
    rng = np.random.default_rng(seed)
    assets = [get_object(n) for n in sc.objects]
    t0 = time.perf_counter()
    attempts = 1 if sc.poses is not None else cfg.max_resamples
    last: list[str] = []
    for attempt in range(1, attempts + 1):
        layout = place_scene(sc, rng, placement)
        poses = layout.objects
        spec, rcfg, robot_geoms = _new_spec(robot)
        _setup_scene(spec, cfg, robot=rcfg is not None)
        fixture = _add_fixture(spec, sc.fixture, layout.fixture) if layout.fixture is not None else None
        _add_object_assets(spec, assets)
        for k, (a, p) in enumerate(zip(assets, poses, strict=True), start=1):
            _add_object(spec, k, a, p, cfg.drop_height)
        model, data = _compile(spec, f"scenario {sc.name!r}")
        ids = None
        if rcfg is not None:
            ids = rcfg.resolve(model)
            _set_robot_home(data, rcfg, ids)
        if realism is not None:
            _apply_realism(model, assets, ids, realism)
        objects, g2i = _object_records(model, sc, assets, poses)
        world = World(model=model, data=data, spec=spec, scenario=sc.name, scenario_spec=sc, seed=seed,
                      objects=objects, geom_to_instance=g2i, robot=None if rcfg is None else _robot_label(robot),
                      robot_config=rcfg, robot_ids=ids, robot_geom_ids=np.array([g.id for g in robot_geoms], int),
                      layout_attempts=attempt, realism=realism, fixture=fixture)
        for o in objects:
            o._world = world
        mujoco.mj_forward(model, data)
        poses0 = [o.T_world_obj for o in objects]
        n_steps = int(round(cfg.settle_time / model.opt.timestep))
        mujoco.mj_step(model, data, nstep=max(n_steps, 1))
        mujoco.mj_forward(model, data)
        last = _settle_problems(world, poses0, cfg)
        if not last:
            world._settled = {"qpos": data.qpos.copy(), "ctrl": data.ctrl.copy(), "act": data.act.copy()}
            world.reset()
            log.debug("built %s seed %d in %.2f s (%d layout(s))", sc.name, seed, time.perf_counter() - t0, attempt)
            return world
        log.info("scenario %s seed %d layout %d rejected: %s", sc.name, seed, attempt, "; ".join(last))
    raise SceneError(f"scenario {sc.name!r} seed {seed}: no layout settled cleanly in {attempts} attempt(s); "
                     f"last problems: {'; '.join(last)}")


def _apply_realism(model: mujoco.MjModel, assets: list[ObjectAsset], ids: RobotIds | None,
                   realism: RealismRecord) -> None:
    """Contact and mass values of ``realism`` into the compiled model (see :func:`sim.realism.apply_physics`)."""
    from sim.realism import apply_physics

    bodies = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"obj{k}_{a.name}") for k, a in
              enumerate(assets, start=1)]
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] in bodies and model.geom_group[g] == GROUP_COLLISION]
    pads = list(ids.pads) if ids is not None else []
    apply_physics(realism, model, bodies, geoms, pads, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table"))


def _robot_label(robot: str | Path | RobotConfig) -> str:
    return robot.name if hasattr(robot, "arm") else str(robot)


def _object_records(
    model: mujoco.MjModel, sc: Scenario, assets: list[ObjectAsset], poses: list[Placement]
) -> tuple[tuple[WorldObject, ...], np.ndarray]:
    g2i = np.zeros(model.ngeom, dtype=np.int32)
    out = []
    for k, (a, p) in enumerate(zip(assets, poses, strict=True), start=1):
        bname = f"obj{k}_{a.name}"
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, bname)
        gids = np.nonzero(model.geom_bodyid == bid)[0]
        g2i[gids] = k
        vis = tuple(int(g) for g in gids if model.geom_group[g] in (GROUP_GLASS, GROUP_OPAQUE))
        col = tuple(int(g) for g in gids if model.geom_group[g] == GROUP_COLLISION)
        out.append(WorldObject(instance_id=k, name=a.name, body_name=bname, body_id=int(bid), visual_geom_ids=vis,
                               collision_geom_ids=col, mass=float(model.body_mass[bid]), transparent=a.transparent,
                               mesh=a.mesh, placement=p))
    return tuple(out), g2i


def check_world(world: World, seconds: float = 1.0, max_move: float = 0.005) -> dict[str, float]:
    """Step a copy of ``world.data`` for ``seconds``; raise SceneError on MuJoCo warnings or objects moving.

    Returns ``{"max_move_m": ..., "max_tilt_deg": ...}`` over all objects. ``world.data`` is untouched.
    """
    m = world.model
    d = copy.copy(world.data)
    start = [world.object_pose(o.instance_id) for o in world.objects]
    mujoco.mj_step(m, d, nstep=max(1, int(round(seconds / m.opt.timestep))))
    warn = _warnings(d)
    if warn:
        raise SceneError(f"scenario {world.scenario!r} seed {world.seed}: MuJoCo warnings while stepping: {warn}")
    moves, tilts = [0.0], [0.0]
    for o, T0 in zip(world.objects, start, strict=True):
        adr = m.jnt_qposadr[m.body_jntadr[o.body_id]]
        pos = d.qpos[adr:adr + 3]
        moves.append(float(np.linalg.norm(pos - T0[:3, 3])))
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, d.qpos[adr + 3:adr + 7])
        tilts.append(_tilt_deg(mat.reshape(3, 3)))
    if max(moves) > max_move:
        k = int(np.argmax(moves))  # index into [0.0] + objects
        raise SceneError(f"scenario {world.scenario!r} seed {world.seed}: object {k} moved {moves[k] * 1e3:.1f} mm "
                         f"in {seconds} s (limit {max_move * 1e3:.1f} mm)")
    return {"max_move_m": max(moves), "max_tilt_deg": max(tilts)}
