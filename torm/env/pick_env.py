"""``torm/TormPick-v0``: a low-level pick env for RL on the simulated robot (MuJoCo, simulation only).

Action (``Box(7,) float32``): an end-effector delta pose and a gripper command,
``[dx, dy, dz, droll, dpitch, dyaw, grip]``. With ``action_mode="normalized"`` (default) every component is
in [-1, 1] and maps linearly to the physical limits: the TCP target moves by ``a[:3] * max_pos_step`` m in the
world frame and turns by the extrinsic world-axis rotation ``a[3:6] * max_rot_step`` rad about the TCP; with
``action_mode="raw"`` the action is in those physical units (m, rad per step) and the box is
``[-max_pos_step, max_pos_step]^3 x [-max_rot_step, max_rot_step]^3 x [-1, 1]``. ``grip`` in [-1, 1] (both modes)
maps linearly to the pad gap, -1 = fully open (the gripper's stroke), +1 = fully closed. An action outside the
box is clipped into it (``out_of_bounds="clip"``, default; ``info["action_clipped"]`` says so) or refused with
:class:`~torm.env.errors.InvalidActionError` naming the bounds (``out_of_bounds="raise"``); a wrong shape or a
NaN/inf component is always refused.

Each step: the TCP target is clipped into ``tcp_box`` (``info["clipped"]``), IK (mink, :class:`IKSolver`) solves
the arm joints from the current joint targets; an unreachable target, or one that needs joints faster than
``speed_scale`` x the joint speed limits, is rejected (the arm holds its previous target,
``info["rejected"]`` names why). The env then streams linearly interpolated joint targets and the gripper
command into the position actuators for ``control_period`` s of simulated time, stepping physics through the
backend's clock (so the backend's health checks run every tick; a :class:`PhysicsError` terminates the episode
with ``info["physics_error"]``). The gripper command is applied at once (not blocking), the fingers move at the
actuator's own speed, with the actuator's force limit.

Observation (``Dict``): ``joint_pos`` (n,) rad, ``joint_vel`` (n,) rad/s, ``tcp_pose`` (7,) = position (m) +
quaternion wxyz in the world frame, ``gripper_width`` (1,) m, and per camera in ``cameras``
``<cam>_rgb`` (H, W, 3) uint8 and, with ``depth``, ``<cam>_depth`` (H, W) float32 z-depth in m
(cameras: ``overview`` fixed, ``wrist`` rigidly mounted behind the TCP; see :mod:`torm.env.cameras`).
With ``privileged_state`` the target object's position (3,) m and quaternion wxyz (4,) are added
(``object_pos``, ``object_quat``) for state-based baselines. ``obs_mode`` names these the way ManiSkill does:
``state`` (no cameras), ``rgb``, ``rgbd``, ``pointcloud`` (``pointcloud_xyz`` (N, 3) m world frame +
``pointcloud_rgb`` (N, 3) uint8 back-projected from the cameras' depth, N = ``pointcloud_points``, sampled with the
env's seeded RNG); ``control_mode="pd_ee_delta_pose"`` names the action.

Success (the paper's test, Sec. IV-E, judged from the true object pose): with ``success="lift"`` (default)
the target object is *lifted*: raised at least ``lift_height - height_tolerance`` (0.24 m) above its rest
height while *held* (both pads touch it and its origin is within ``held_distance`` of the TCP). With
``success="lift_translate"`` the lift is stage one and the episode succeeds once the held, still-lifted object
has also moved ``translation - slip_tolerance`` (0.18 m) horizontally from its rest position (stage two).
The (lower, release) part of the paper's test is not required in this env.

Reward: ``success_reward`` (1.0) on the success step, 0 otherwise; with ``reward_shaping`` a dense term is
added every step: ``w_reach * (1 - tanh(reach_scale * d))`` (d = TCP-to-object distance, m; ``reach_scale``
10 / m by default) + ``w_grasp`` when both pads touch the object + ``w_lift * clip(lift / lift_height, 0, 1)``
while held (+ ``w_translate`` x the translation fraction in ``lift_translate`` mode); default weights 0.1, 0.25,
0.5, 0.25. Termination: success or physics error.
Truncation: ``gymnasium.make`` wraps the env in a ``TimeLimit`` of :data:`torm.env.PICK_MAX_EPISODE_STEPS`
(200) steps (the registered spec's ``max_episode_steps``; change it with
``gymnasium.make(id, max_episode_steps=N)``); a directly constructed env truncates only when its config's
``max_episode_steps`` is set.

Seeding: ``reset(seed=s)`` builds the scenario's layout from seed ``s`` (the same seed gives the same layout
and, for the same actions, the same rollout). ``reset()`` without a seed keeps the fixed ``layout_seed`` when
one is configured, else draws the layout seed from the env's RNG (seeded by the last seeded reset).
``reset(options={"layout_seed": k})`` picks layout ``k`` explicitly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from torm.config import with_options
from torm.env.cameras import CAMERA_NAMES, MAX_DEPTH, EnvCameras, WristMount
from torm.env.errors import InvalidActionError
from torm.errors import ConfigError, UnknownNameError
from torm.execution.errors import PhysicsError
from torm.execution.ik import IKConfig
from torm.execution.success import SuccessCriteria
from torm.runtime import close_at_exit

log = logging.getLogger(__name__)

SUCCESS_MODES = ("lift", "lift_translate")
#: observation modes, as ManiSkill names them (``obs_mode``); None keeps ``cameras`` / ``depth`` as configured
OBS_MODES = ("state", "rgb", "rgbd", "pointcloud")
#: control modes (``control_mode``), as ManiSkill names them: the end-effector delta pose + gripper of this env
CONTROL_MODES = ("pd_ee_delta_pose",)
ACTION_MODES = ("normalized", "raw")
OUT_OF_BOUNDS = ("clip", "raise")
#: Observation bounds: positions within this many metres of the base; joint speeds within this factor x limits.
POSITION_BOUND = 3.0
JOINT_SPEED_BOUND_FACTOR = 10.0


@dataclass(frozen=True)
class PickEnvConfig:
    """Settings of :class:`TormPickEnv` (m, rad, s).

    Attributes:
        scenario: scenario name (``torm scenes list``), e.g. "rw1" (one glass cylinder).
        robot: robot folder name.
        layout_seed: fixed layout seed for unseeded resets; None draws one from the env RNG per reset.
        target_object: instance id (1-based) of the object whose pick counts.
        cameras: camera observations, subset of ("overview", "wrist"); empty for state-only observations.
        image_size: (H, W) of the observation images (pixels).
        depth: also return a depth image per camera.
        render_size: (H, W) of ``render()`` images.
        fovy_deg: vertical field of view of the overview camera (deg).
        wrist: placement and field of view of the wrist camera.
        privileged_state: add the target object's true pose to the observation.
        control_period: simulated time per env step (s).
        action_mode: "normalized" (actions in [-1, 1] scaled to the limits below) or "raw" (m, rad per step).
        out_of_bounds: "clip" (clip into the action box) or "raise" (InvalidActionError naming the bounds).
        max_pos_step: largest TCP translation per step on each axis (m).
        max_rot_step: largest TCP rotation per step about each world axis (rad).
        tcp_box: ((x, y, z)_min, (x, y, z)_max) box the TCP target is clipped into (m).
        speed_scale: fraction of the joint speed limits a step may need before it is rejected, (0, 1].
        ik: IK tolerances.
        max_episode_steps: truncation horizon counted by the env itself (steps); None = leave it to gymnasium's
            TimeLimit (the registered spec uses 200).
        success: "lift" or "lift_translate" (see the module docstring).
        criteria: lift height, translation and tolerances of the success test.
        held_distance: largest object-origin-to-TCP distance that counts as "in the hand" (m).
        success_reward: reward on the success step.
        reward_shaping: add the dense shaping terms.
        w_reach, w_grasp, w_lift, w_translate: shaping weights.
        reach_scale: the reach term's distance scale (1/m): ``1 - tanh(reach_scale * d)`` (ManiSkill's PickCube
            uses 5; 10 rewards only the last ~10 cm).
        obs_mode: ManiSkill's observation vocabulary: ``state`` (proprioception only, no cameras), ``rgb``
            (``cameras`` without depth), ``rgbd`` (with depth), ``pointcloud`` (``pointcloud_xyz`` (N, 3) m world
            frame and ``pointcloud_rgb`` (N, 3) uint8 from the cameras' depth instead of images); None = as
            ``cameras`` and ``depth`` say.
        control_mode: ``pd_ee_delta_pose`` (the only one: a TCP delta pose and a gripper command, position-
            controlled joints), ManiSkill's name for what the action is.
        pointcloud_points: N of the ``pointcloud`` observation.
        realism: the harness's realism profile (``ideal``, ``measured``, ``stress``): contact, object mass,
            calibration and execution errors drawn per layout from the sourced ranges (:mod:`sim.realism`); the
            draw is in the reset ``info`` (``realism_drawn``).
        stress: the multiplier of the ``stress`` profile.
    """

    scenario: str = "rw1"
    robot: str = "inovo_2f85"
    layout_seed: int | None = None
    target_object: int = 1
    cameras: tuple[str, ...] = ("overview",)
    image_size: tuple[int, int] = (96, 96)
    depth: bool = True
    render_size: tuple[int, int] = (240, 320)
    fovy_deg: float = 60.0
    wrist: WristMount = field(default_factory=WristMount)
    privileged_state: bool = False
    control_period: float = 0.1
    action_mode: str = "normalized"
    out_of_bounds: str = "clip"
    max_pos_step: float = 0.02
    max_rot_step: float = 0.1
    tcp_box: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.15, -0.5, 0.02), (0.95, 0.5, 0.7))
    speed_scale: float = 0.5
    ik: IKConfig = field(default_factory=IKConfig)
    max_episode_steps: int | None = None
    success: str = "lift"
    criteria: SuccessCriteria = field(default_factory=SuccessCriteria)
    held_distance: float = 0.15
    success_reward: float = 1.0
    reward_shaping: bool = False
    w_reach: float = 0.1
    w_grasp: float = 0.25
    w_lift: float = 0.5
    w_translate: float = 0.25
    reach_scale: float = 10.0
    obs_mode: str | None = None
    control_mode: str = "pd_ee_delta_pose"
    pointcloud_points: int = 1024
    realism: str = "ideal"
    stress: float = 1.0

    def __post_init__(self) -> None:
        from torm.pipeline import REALISM_PROFILES

        if self.realism not in REALISM_PROFILES:
            raise UnknownNameError("realism", self.realism, REALISM_PROFILES)
        if not (np.isfinite(self.stress) and self.stress >= 1):
            raise ConfigError(f"PickEnvConfig.stress must be >= 1, got {self.stress}")
        if self.obs_mode is not None and self.obs_mode not in OBS_MODES:
            raise UnknownNameError("obs_mode", self.obs_mode, OBS_MODES)
        if self.control_mode not in CONTROL_MODES:
            raise UnknownNameError("control_mode", self.control_mode, CONTROL_MODES)
        if self.pointcloud_points < 1:
            raise ConfigError(f"PickEnvConfig.pointcloud_points must be >= 1, got {self.pointcloud_points}")
        if self.obs_mode == "state":
            object.__setattr__(self, "cameras", ())
        elif self.obs_mode is not None:
            if not tuple(self.cameras):
                raise ConfigError(f"obs_mode {self.obs_mode!r} needs at least one camera in cameras")
            object.__setattr__(self, "depth", self.obs_mode in ("rgbd", "pointcloud"))
        cams = tuple(self.cameras)
        bad = [c for c in cams if c not in CAMERA_NAMES]
        if bad:
            raise UnknownNameError("camera", bad[0], CAMERA_NAMES)
        if len(set(cams)) != len(cams):
            raise ConfigError(f"PickEnvConfig.cameras {cams} lists a camera twice")
        object.__setattr__(self, "cameras", cams)
        for name in ("image_size", "render_size"):
            hw = tuple(int(v) for v in getattr(self, name))
            if len(hw) != 2 or min(hw) < 8:
                raise ConfigError(f"PickEnvConfig.{name} must be (H, W) with both >= 8 pixels, got {hw}")
            object.__setattr__(self, name, hw)
        if self.success not in SUCCESS_MODES:
            raise UnknownNameError("success mode", self.success, SUCCESS_MODES)
        if self.action_mode not in ACTION_MODES:
            raise UnknownNameError("action_mode", self.action_mode, ACTION_MODES)
        if self.out_of_bounds not in OUT_OF_BOUNDS:
            raise UnknownNameError("out_of_bounds", self.out_of_bounds, OUT_OF_BOUNDS)
        for name in ("control_period", "max_pos_step", "max_rot_step", "held_distance"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"PickEnvConfig.{name} must be positive, got {getattr(self, name)}")
        if not 0.0 < self.speed_scale <= 1.0:
            raise ConfigError(f"PickEnvConfig.speed_scale must be in (0, 1], got {self.speed_scale}")
        if (self.max_episode_steps is not None and self.max_episode_steps < 1) or self.target_object < 1:
            raise ConfigError("PickEnvConfig.max_episode_steps and target_object must be >= 1")
        lo, hi = (np.asarray(b, float) for b in self.tcp_box)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
            raise ConfigError(f"PickEnvConfig.tcp_box must be ((x, y, z)_min, (x, y, z)_max) with max > min, "
                              f"got {self.tcp_box}")
        object.__setattr__(self, "tcp_box", (tuple(lo.tolist()), tuple(hi.tolist())))
        if self.layout_seed is not None and self.layout_seed < 0:
            raise ConfigError(f"PickEnvConfig.layout_seed must be >= 0 or None, got {self.layout_seed}")


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


class TormPickEnv(gym.Env):
    """Low-level pick env (see the module docstring). ``config`` or keyword options of :class:`PickEnvConfig`."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, config: PickEnvConfig | dict | None = None, render_mode: str | None = None,
                 **options: Any) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise UnknownNameError("render_mode", render_mode, self.metadata["render_modes"])
        self.config = cfg = with_options(PickEnvConfig, config, options)
        self.render_mode = render_mode
        from sim.robots.config import load_robot_config

        self._rcfg = load_robot_config(cfg.robot, validate=False)
        #: physical size of one unit of each normalised action component (m, m, m, rad, rad, rad, grip)
        self.action_scale = np.array([cfg.max_pos_step] * 3 + [cfg.max_rot_step] * 3 + [1.0])
        hi = np.ones(7, np.float32) if cfg.action_mode == "normalized" else self.action_scale.astype(np.float32)
        self.action_space = spaces.Box(-hi, hi, dtype=np.float32)
        qd = JOINT_SPEED_BOUND_FACTOR * np.asarray(self._rcfg.arm.velocity_limits, np.float32)
        pose_hi = np.array([POSITION_BOUND] * 3 + [1.0] * 4, np.float32)
        obs: dict[str, spaces.Space] = {
            "joint_pos": spaces.Box(np.asarray(self._rcfg.arm.lower, np.float32),
                                    np.asarray(self._rcfg.arm.upper, np.float32), dtype=np.float32),
            "joint_vel": spaces.Box(-qd, qd, dtype=np.float32),
            "tcp_pose": spaces.Box(-pose_hi, pose_hi, dtype=np.float32),
            "gripper_width": spaces.Box(0.0, float(self._rcfg.gripper.geometry.max_opening) + 0.01, (1,), np.float32),
        }
        H, W = cfg.image_size
        if cfg.obs_mode == "pointcloud":
            N = cfg.pointcloud_points
            obs["pointcloud_xyz"] = spaces.Box(-POSITION_BOUND, POSITION_BOUND, (N, 3), np.float32)
            obs["pointcloud_rgb"] = spaces.Box(0, 255, (N, 3), np.uint8)
        else:
            for cam in cfg.cameras:
                obs[f"{cam}_rgb"] = spaces.Box(0, 255, (H, W, 3), np.uint8)
                if cfg.depth:
                    obs[f"{cam}_depth"] = spaces.Box(0.0, MAX_DEPTH, (H, W), np.float32)
        if cfg.privileged_state:
            obs["object_pos"] = spaces.Box(-POSITION_BOUND, POSITION_BOUND, (3,), np.float32)
            obs["object_quat"] = spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = spaces.Dict(obs)
        self._world = None
        self._backend = None
        self._cams: EnvCameras | None = None
        self._render_cams: EnvCameras | None = None
        self._layout: int | None = None
        self._steps = 0
        self._physics_error: str | None = None

    # ------------------------------------------------------------------------------------------ building
    @property
    def backend(self):
        """The :class:`sim.backend.SimBackend` of the current layout (None before the first reset)."""
        return self._backend

    @property
    def world(self):
        """The :class:`sim.world.World` of the current layout (None before the first reset)."""
        return self._world

    def _free_cameras(self) -> None:
        for c in (self._cams, self._render_cams):
            if c is not None:
                c.close()
        self._cams = self._render_cams = None

    def _build(self, layout_seed: int) -> None:
        from sim.backend import SimBackend
        from sim.world import build_world
        from torm.execution.pick import make_ik_solver

        cfg = self.config
        self._free_cameras()
        if self._backend is not None:
            self._backend.close()
        realism = None
        if cfg.realism != "ideal":  # drawn per layout from the sourced ranges, as a harness trial draws them
            from sim.realism import sample_scenario_realism

            realism = sample_scenario_realism(cfg.realism, cfg.scenario, int(layout_seed), stress=cfg.stress)
        world = build_world(cfg.scenario, int(layout_seed), robot=cfg.robot, realism=realism)
        if cfg.target_object > len(world.objects):
            raise ConfigError(f"target_object {cfg.target_object} but scenario {cfg.scenario!r} has objects "
                              f"1..{len(world.objects)}")
        self._world, self._layout = world, int(layout_seed)
        self._backend = SimBackend(world, realism=realism)
        self._ik_factory = lambda: make_ik_solver(self._rcfg, cfg.ik)
        m = world.model
        arm = self._rcfg.arm
        ids = world.robot_ids  # actuators resolved from their joints when the MJCF leaves them unnamed
        self._arm_act = np.asarray(ids.arm_actuators)
        self._grip_act = int(ids.gripper_actuator)
        self._fingers = (frozenset(ids.left_pads), frozenset(ids.right_pads))
        obj = world.objects[cfg.target_object - 1]
        self._obj_geoms = set(int(g) for g in obj.collision_geom_ids)
        self._obj_offset = obj.mesh.bounding_box.centroid.copy()  # body origin -> bbox centre (body frame, m)
        g = self._rcfg.gripper.geometry
        kw = dict(tcp_site=arm.tcp_site, approach_axis=str(g.approach_axis), closing_axis=str(g.closing_axis),
                  mount=cfg.wrist, fovy_deg=cfg.fovy_deg)
        if cfg.cameras:
            self._cams = EnvCameras(m, world.data, *cfg.image_size, **kw)
        if self.render_mode == "rgb_array":
            self._render_cams = EnvCameras(m, world.data, *cfg.render_size, **kw)

    # ------------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"layout_seed"}
        if unknown:
            raise UnknownNameError("reset option", sorted(unknown)[0], ["layout_seed"])
        if options.get("layout_seed") is not None:
            layout = int(options["layout_seed"])
        elif seed is not None:
            layout = int(seed)
        elif self.config.layout_seed is not None:
            layout = self.config.layout_seed
        else:
            layout = int(self.np_random.integers(0, 2**31 - 1))
        if layout != self._layout or self._backend is None:
            self._build(layout)
        else:
            self._backend.reset()
        self._ik = self._ik_factory()
        st = self._backend.arm.state()
        self._T_target = st.T_world_tcp.copy()
        self._q_cmd = self._world.data.ctrl[self._arm_act].copy()
        self._grip_cmd = float(self._world.data.ctrl[self._grip_act])
        self._rest = self._object_pos()
        self._lifted = False
        self._steps = 0
        self._physics_error = None
        info = self._info(clipped=False, rejected=None, success=False)
        realism = self._backend.realism
        info.update(layout_seed=self._layout, realism=self.config.realism,
                    realism_drawn=realism.as_dict() if realism is not None else {"profile": "ideal"})
        close_at_exit(self)  # an env left open is closed at exit before EGL terminates (torm.runtime)
        return self._observation(), info

    def step(self, action):
        if self._backend is None:
            raise ConfigError("call reset() before step()")
        a, action_clipped = self._check_action(action)
        cfg = self.config
        clipped, rejected = False, None
        T_new = self._T_target.copy()
        T_new[:3, 3] = self._T_target[:3, 3] + a[:3]
        lo, hi = (np.asarray(b) for b in cfg.tcp_box)
        p = np.clip(T_new[:3, 3], lo, hi)
        clipped = bool(np.any(p != T_new[:3, 3]))
        T_new[:3, 3] = p
        if np.any(a[3:6] != 0):
            T_new[:3, :3] = Rotation.from_euler("xyz", a[3:6]).as_matrix() @ self._T_target[:3, :3]
        q_new = self._q_cmd
        res = self._ik.solve(T_new, self._q_cmd, self._q_cmd)
        if not res.converged:
            rejected = f"unreachable (IK residual {res.pos_err * 1000:.1f} mm / {np.degrees(res.rot_err):.1f} deg)"
        else:
            v = np.abs(res.q - self._q_cmd) / cfg.control_period
            vmax = np.asarray(self._rcfg.arm.velocity_limits) * cfg.speed_scale
            if np.any(v > vmax):
                j = int(np.argmax(v / vmax))
                rejected = f"joint {j} would move at {v[j]:.2f} rad/s > {vmax[j]:.2f} rad/s"
            else:
                q_new, self._T_target = res.q, T_new
        width = 0.5 * (1.0 - float(a[6])) * self._rcfg.gripper.geometry.max_opening
        lo_c, hi_c = sorted(self._rcfg.gripper.command_range)
        self._grip_cmd = float(np.clip(self._rcfg.gripper.width_to_command(width), lo_c, hi_c))
        terminated = False
        try:
            self._run(q_new)
        except PhysicsError as exc:
            self._physics_error = str(exc)
            terminated = True
            log.warning("TormPick episode ended by a physics error: %s", exc)
        self._q_cmd = q_new
        self._steps += 1
        success, stage_info = self._success() if self._physics_error is None else (False, {})
        reward = cfg.success_reward if success else 0.0
        if cfg.reward_shaping and self._physics_error is None:
            reward += self._shaping(stage_info)
        terminated = terminated or success
        truncated = (not terminated) and cfg.max_episode_steps is not None and self._steps >= cfg.max_episode_steps
        info = self._info(clipped, rejected, success, stage_info)
        info["action_clipped"] = action_clipped
        return self._observation(), float(reward), terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array" or self._render_cams is None:
            return None
        img = self._render_cams.render(["scene"], depth=False)["scene_rgb"]
        close_at_exit(self)
        return img

    def close(self) -> None:
        self._free_cameras()
        if self._backend is not None:
            self._backend.close()
        self._backend = None
        self._world = None
        self._layout = None

    # ------------------------------------------------------------------------------------------ internals
    def _check_action(self, action) -> tuple[np.ndarray, bool]:
        """The action in physical units (m, rad per step; grip -1..1) and whether it had to be clipped."""
        box = self.action_space
        units = "normalised, -1..1" if self.config.action_mode == "normalized" else "m, rad per step; grip -1..1"
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InvalidActionError(f"action {action!r} is not numeric; give 7 floats within "
                                     f"{box.low.tolist()}..{box.high.tolist()} ({units})") from exc
        if a.shape != box.shape:
            raise InvalidActionError(f"action has shape {a.shape}, expected {box.shape}: [dx, dy, dz, droll, "
                                     f"dpitch, dyaw, grip (-1 open .. 1 closed)] ({units})")
        names = ["dx", "dy", "dz", "droll", "dpitch", "dyaw", "grip"]
        if not np.all(np.isfinite(a)):
            i = int(np.argmax(~np.isfinite(a)))
            raise InvalidActionError(f"action[{i}] ({names[i]}) = {a[i]!r} is not finite (NaN/inf is never clipped); "
                                     f"give values within [{box.low[i]:g}, {box.high[i]:g}] ({units})")
        tol = 1e-6
        bad = (a < box.low - tol) | (a > box.high + tol)
        if np.any(bad) and self.config.out_of_bounds == "raise":
            i = int(np.argmax(bad))
            raise InvalidActionError(
                f"action[{i}] ({names[i]}) = {a[i]!r} is outside [{box.low[i]:g}, {box.high[i]:g}]; the action "
                f"bounds are low={box.low.tolist()} high={box.high.tolist()} ({units}); set out_of_bounds='clip' "
                "to clip instead")
        a = np.clip(a, box.low, box.high)
        if self.config.action_mode == "normalized":
            a = a * self.action_scale
        return a, bool(np.any(bad))

    def _run(self, q_new: np.ndarray) -> None:
        """Stream joint targets (linear from the previous targets) and the gripper command for one period."""
        d = self._world.data
        b = self._backend
        dt = b.config.control_dt
        n = max(1, int(round(self.config.control_period / dt)))
        q0 = self._q_cmd
        d.ctrl[self._grip_act] = self._grip_cmd
        for k in range(1, n + 1):
            d.ctrl[self._arm_act] = q0 + (k / n) * (q_new - q0)
            b.clock.sleep(dt)

    def _object_pos(self) -> np.ndarray:
        """Target object's bounding-box centre in the world (m)."""
        T = self._world.object_pose(self.config.target_object)
        return T[:3, :3] @ self._obj_offset + T[:3, 3]

    def _pad_contacts(self) -> int:
        """How many of the two fingers touch the target object with one of their pads."""
        d = self._world.data
        touching = set()
        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom1), int(c.geom2)
            for k, pads in enumerate(self._fingers):
                if (g1 in pads and g2 in self._obj_geoms) or (g2 in pads and g1 in self._obj_geoms):
                    touching.add(k)
        return len(touching)

    def _success(self) -> tuple[bool, dict[str, Any]]:
        c = self.config.criteria
        p = self._object_pos()
        tcp = self._backend.arm.state().T_world_tcp[:3, 3]
        dist = float(np.linalg.norm(p - tcp))
        pads = self._pad_contacts()
        held = pads == 2 and dist < self.config.held_distance
        lift = float(p[2] - self._rest[2])
        moved = float(np.linalg.norm((p - self._rest)[:2]))
        lifted = held and lift >= c.lift_height - c.height_tolerance
        self._lifted = self._lifted or lifted
        if self.config.success == "lift":
            ok = lifted
        else:
            ok = self._lifted and lifted and moved >= c.translation - c.slip_tolerance
        info = {"lift_m": lift, "translation_m": moved, "tcp_object_distance_m": dist, "pad_contacts": pads,
                "held": held, "lifted": self._lifted}
        return bool(ok), info

    def _shaping(self, s: dict[str, Any]) -> float:
        cfg = self.config
        r = cfg.w_reach * (1.0 - np.tanh(cfg.reach_scale * s["tcp_object_distance_m"]))
        r += cfg.w_grasp * (s["pad_contacts"] == 2)
        if s["held"]:
            r += cfg.w_lift * float(np.clip(s["lift_m"] / cfg.criteria.lift_height, 0.0, 1.0))
            if cfg.success == "lift_translate" and s["lifted"]:
                r += cfg.w_translate * float(np.clip(s["translation_m"] / cfg.criteria.translation, 0.0, 1.0))
        return float(r)

    def _observation(self) -> dict[str, np.ndarray]:
        st = self._backend.arm.state()
        T = st.T_world_tcp
        obs = {
            "joint_pos": st.q.astype(np.float32),
            "joint_vel": st.qd.astype(np.float32),
            "tcp_pose": np.concatenate([T[:3, 3], _quat_wxyz(T[:3, :3])]).astype(np.float32),
            "gripper_width": np.array([self._backend.gripper.width()], np.float32),
        }
        if self._cams is not None and self.config.obs_mode == "pointcloud":
            xyz, rgb = self._cams.pointcloud(self.config.cameras, self.config.pointcloud_points, self.np_random)
            obs.update(pointcloud_xyz=xyz, pointcloud_rgb=rgb)
        elif self._cams is not None:
            obs.update(self._cams.render(self.config.cameras, depth=self.config.depth))
        if self.config.privileged_state:
            To = self._world.object_pose(self.config.target_object)
            obs["object_pos"] = self._object_pos().astype(np.float32)
            obs["object_quat"] = _quat_wxyz(To[:3, :3]).astype(np.float32)
        for k, v in obs.items():  # a blown-up simulation (or a joint a hair past its limit) stays in the space
            if v.dtype == np.float32:
                box = self.observation_space[k]
                obs[k] = np.clip(np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0), box.low, box.high)
        return obs

    def _info(self, clipped: bool, rejected: str | None, success: bool,
              stage: dict[str, Any] | None = None) -> dict[str, Any]:
        info: dict[str, Any] = {"layout_seed": self._layout, "steps": self._steps, "clipped": clipped,
                                "rejected": rejected is not None, "rejected_reason": rejected or "",
                                "is_success": bool(success), "sim_time_s": float(self._world.data.time)}
        if self._physics_error is not None:
            info["physics_error"] = self._physics_error
        info.update(stage or {})
        return info
