"""Measure a gripper in simulation and print the robot.yaml entries: width map, TCP offset, grip-force map.

Run (``ROBOT`` = a folder name under sim/robots or a robot.yaml path; each prints YAML to paste)::

    python -m sim.robots.measure_gripper ROBOT                 # gripper.command_to_width (nothing between pads)
    python -m sim.robots.measure_gripper ROBOT --tcp-offset    # gripper.tcp_offset (pad centre along the approach)
    python -m sim.robots.measure_gripper ROBOT --force         # gripper.force_map (fixed blocks, contact forces)
    python -m sim.robots.measure_gripper ROBOT --check-force   # requested vs measured pad force with the YAML's map

The rig: the robot alone (composed like in the world, with the world's contact options), gravity off, the arm
held at ``arm.home`` (its joints reset every step, so neither arm sag nor servo error enters). Units: m, s, N.

* Width: open fully, command, settle ``duration_s``; the gap is the smallest signed distance between a left and
  a right pad geom (``mj_geomDistance``, exact for any pad shape).
* TCP offset: in the same states, the mean of the pad geoms' centres projected on the TCP approach axis,
  relative to the TCP site.
* Force: a fixed box (no joint) of the given width along the closing axis, centred between the pads at the
  measured TCP offset. For each setting ``s`` the gripper actuator's force range is set to ``(-s, s)``, the
  gripper opens to 10 mm more than the block, commands closed and settles; the pad force is each finger's summed
  normal contact force on the block (``mj_contactForce``), averaged over the fingers
  (:func:`sim.robots.force_map.measured_pad_force`). ``max_force`` is the same with the force limit removed. Settings
  default to a range scaled so the pad force spans about 10-300 N (from one probe at the MJCF's own force limit).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import yaml

from sim.robots.config import RobotConfig, load_robot_config
from sim.robots.force_map import ForceMap, measured_pad_force, pad_distance

DEFAULT_COMMANDS = (0, 32, 64, 96, 128, 160, 192, 224, 255)
#: Pad forces (N) the default settings aim to span (the 2F-85's 20-235 N with margin on both sides).
TARGET_FORCES = (10.0, 20.0, 40.0, 80.0, 130.0, 180.0, 235.0, 300.0)
_AXES = "xyz"


def pad_gap(model: mujoco.MjModel, data: mujoco.MjData, pad_geoms: Sequence) -> float:
    """Signed distance (m) between the pads in ``data`` (negative = interpenetrating).

    ``pad_geoms`` is ``[left, right]`` names or ``[[left names...], [right names...]]``.
    """
    sides = [[p] if isinstance(p, str) else list(p) for p in pad_geoms]
    ids = [[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in side] for side in sides]
    return pad_distance(model, data, ids[0], ids[1])


@dataclass
class Rig:
    """The robot held at home with gravity off, optionally with a fixed block between the pads."""

    cfg: RobotConfig
    model: mujoco.MjModel
    block: int = -1

    @classmethod
    def build(cls, cfg: RobotConfig, block_width: float | None = None) -> Rig:
        from sim.world import physics_options

        spec = cfg.robot_spec()
        physics_options(spec)
        spec.option.gravity = (0.0, 0.0, 0.0)
        block = None
        if block_width is not None:
            T = cls(cfg, spec.copy().compile()).tcp_pose()
            g = cfg.gripper.geometry
            a, c = _AXES.index(g.approach_axis), _AXES.index(g.closing_axis)
            size = np.array(g.pad_size, float) + 0.01
            size[c] = block_width
            size[a] = g.pad_size[a] + 0.01
            centre = T[:3, 3] + cfg.gripper.tcp_offset_m(block_width) * T[:3, a]
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, T[:3, :3].ravel())
            block = spec.worldbody.add_geom(name="measure_block", type=mujoco.mjtGeom.mjGEOM_BOX,
                                            size=(0.5 * size).tolist(), pos=centre.tolist(), quat=quat.tolist(),
                                            contype=1, conaffinity=1, condim=4, friction=[1.0, 0.01, 0.0001])
        model = spec.compile()
        return cls(cfg, model, -1 if block is None else int(block.id))

    def __post_init__(self) -> None:
        self.ids = self.cfg.resolve(self.model)
        a = self.ids.gripper_actuator
        self._force0 = (int(self.model.actuator_forcelimited[a]), self.model.actuator_forcerange[a].copy())

    def reset(self) -> mujoco.MjData:
        """Fresh data: arm at home, gripper commanded open, the MJCF's own gripper force limit."""
        a = self.ids.gripper_actuator
        self.model.actuator_forcelimited[a], self.model.actuator_forcerange[a] = self._force0
        d = mujoco.MjData(self.model)
        d.qpos[self.ids.arm_qadr] = self.cfg.arm.home_q
        d.ctrl[self.ids.arm_actuators] = self.cfg.arm.home_q
        d.ctrl[self.ids.gripper_actuator] = self.cfg.gripper.open_command
        mujoco.mj_forward(self.model, d)
        return d

    def tcp_pose(self, data: mujoco.MjData | None = None) -> np.ndarray:
        d = data if data is not None else self.reset()
        mujoco.mj_kinematics(self.model, d)
        T = np.eye(4)
        T[:3, :3] = d.site_xmat[self.ids.tcp_site].reshape(3, 3)
        T[:3, 3] = d.site_xpos[self.ids.tcp_site]
        return T

    def run(self, data: mujoco.MjData, command: float, seconds: float) -> None:
        """Hold the arm at home and the gripper at ``command`` for ``seconds``."""
        data.ctrl[self.ids.gripper_actuator] = command
        home = self.cfg.arm.home_q
        for _ in range(max(1, int(round(seconds / self.model.opt.timestep)))):
            data.qpos[self.ids.arm_qadr] = home
            data.qvel[self.ids.arm_dadr] = 0.0
            mujoco.mj_step(self.model, data)
        mujoco.mj_kinematics(self.model, data)

    def gap(self, data: mujoco.MjData) -> float:
        return pad_distance(self.model, data, self.ids.left_pads, self.ids.right_pads)

    def pad_offset(self, data: mujoco.MjData) -> float:
        """Mean pad-geom centre along the TCP approach axis, relative to the TCP site (m)."""
        T = self.tcp_pose(data)
        a = _AXES.index(self.cfg.gripper.geometry.approach_axis)
        centre = data.geom_xpos[list(self.ids.pads)].mean(axis=0)
        return float(np.dot(centre - T[:3, 3], T[:3, a]))

    def set_force_limit(self, setting: float | None) -> None:
        """Force range ``(-setting, setting)`` on the gripper actuator; None removes the limit."""
        a = self.ids.gripper_actuator
        self.model.actuator_forcelimited[a] = 0 if setting is None else 1
        if setting is not None:
            self.model.actuator_forcerange[a] = (-setting, setting)

    def block_force(self, data: mujoco.MjData) -> float:
        ignore = set(range(self.model.ngeom)) - {self.block}
        return measured_pad_force(self.model, data, self.ids.left_pads, self.ids.right_pads, ignore)


def _free_states(cfg: RobotConfig, commands: Sequence[float], duration_s: float):
    rig = Rig.build(cfg)
    for cmd in commands:
        d = rig.reset()
        rig.run(d, cfg.gripper.open_command, 0.5)
        rig.run(d, cmd, duration_s)
        yield rig, d, float(cmd)


def measure_command_to_width(cfg: RobotConfig, commands: Sequence[float] = DEFAULT_COMMANDS,
                             duration_s: float = 1.0) -> list[tuple[float, float]]:
    """[(command, settled pad gap m)] for each command, nothing between the pads, starting open each time."""
    return [(cmd, rig.gap(d)) for rig, d, cmd in _free_states(cfg, commands, duration_s)]


def measure_tcp_offset(cfg: RobotConfig, commands: Sequence[float] = DEFAULT_COMMANDS,
                       duration_s: float = 1.0) -> list[tuple[float, float]]:
    """[(pad gap m, pad-centre position along the approach in the TCP frame m)], gaps increasing."""
    pairs = [(rig.gap(d), rig.pad_offset(d)) for rig, d, _ in _free_states(cfg, commands, duration_s)]
    return sorted(pairs)


def squeeze(cfg: RobotConfig, block_width: float, setting: float | None, rig: Rig | None = None,
            timeout_s: float = 3.0, hold_s: float = 0.2) -> float:
    """Pad force (N) on a fixed block of ``block_width`` (m) with the actuator force limit at ``setting`` (None: no
    limit, the most the gripper squeezes at that width): open to
    10 mm wider than the block, set the limit, command closed, wait until the gap has stayed still (< 0.1 mm/s)
    for ``hold_s`` (at most ``timeout_s``), then read the contact forces."""
    rig = rig or Rig.build(cfg, block_width)
    d = rig.reset()
    g = cfg.gripper
    lo, hi = sorted(g.command_range)
    rig.run(d, g.open_command, 0.3)
    rig.run(d, float(np.clip(g.width_to_command(block_width + 0.01), lo, hi)), 0.3)
    rig.set_force_limit(setting)
    step = 0.02
    still, prev = 0.0, rig.gap(d)
    for _ in range(int(timeout_s / step)):
        rig.run(d, g.closed_command, step)
        gap = rig.gap(d)
        still = still + step if abs(gap - prev) < 1e-4 * step and gap < block_width + 1e-3 else 0.0
        prev = gap
        if still >= hold_s:
            break
    return rig.block_force(d)


def default_widths(cfg: RobotConfig, n: int = 8) -> list[float]:
    """Block widths (m) spanning 15-90 % of the stroke."""
    return [round(float(w), 4) for w in np.linspace(0.15, 0.9, n) * cfg.gripper.geometry.max_opening]


def default_settings(cfg: RobotConfig) -> list[float]:
    """Settings expected to give :data:`TARGET_FORCES`, from probes on a block of half the stroke.

    The pad force per unit setting is read where the force limit binds. A position-servo gripper (force = gain x
    position error, e.g. Menagerie's Panda hand) may squeeze less than its MJCF force limit ever allows: then the
    probe is lowered until the limit binds, and the targets are the ones below the most it squeezes (its
    ``max_force`` at half the stroke or at 90 % of it, whichever is more), or fractions of that most when it
    squeezes less than the smallest target; rows of narrower blocks then level off below them."""
    w = 0.5 * cfg.gripper.geometry.max_opening
    rig = Rig.build(cfg, w)
    cap = squeeze(cfg, w, None, rig)
    if not cap > 0:
        raise SystemExit(f"the gripper produced no pad force on a {w * 1e3:.0f} mm block; check the pad geoms, the "
                         "command direction and the actuator")
    probe = float(rig.model.actuator_forcerange[rig.ids.gripper_actuator][1])
    if not probe > 0:
        probe = 100.0
    force = squeeze(cfg, w, probe, rig)
    for _ in range(16):  # the servo, not the limit, decided: lower the limit until it binds
        if force < 0.9 * cap:
            break
        probe /= 4.0
        force = squeeze(cfg, w, probe, rig)
    ratio = force / probe
    wide = 0.9 * cfg.gripper.geometry.max_opening  # a servo squeezes most where its fingers stop widest
    cap = max(cap, squeeze(cfg, wide, None, Rig.build(cfg, wide)))
    targets = [f for f in TARGET_FORCES if f < 0.9 * cap]
    if len(targets) < 4:
        targets = sorted({*targets, *(round(cap * x, 4) for x in (0.1, 0.25, 0.5, 0.75))})
    return sorted({float(f"{f / ratio:.4g}") for f in targets})


def measure_force_map(cfg: RobotConfig, widths: Sequence[float] | None = None,
                      settings: Sequence[float] | None = None) -> ForceMap:
    """The :class:`ForceMap` measured on fixed blocks (see the module docstring)."""
    widths = list(widths or default_widths(cfg))
    settings = list(settings or default_settings(cfg))
    rows, caps = [], []
    for w in widths:
        rig = Rig.build(cfg, w)
        rows.append(tuple(round(squeeze(cfg, w, s, rig), 2) for s in settings))
        caps.append(round(squeeze(cfg, w, None, rig), 2))
    return ForceMap(tuple(widths), tuple(settings), tuple(rows), tuple(caps))


def check_force(cfg: RobotConfig, forces: Sequence[float], widths: Sequence[float]) -> list[dict[str, float]]:
    """For each width and requested pad force: the force the YAML's map can give there (``applied_n``: the request,
    clipped to the map's range like the backend does), its setting, the measured pad force and the relative error
    (measured / applied - 1)."""
    out = []
    fmap = cfg.gripper.force_map
    for w in widths:
        rig = Rig.build(cfg, w)
        for f in forces:
            applied = float(np.clip(f, *fmap.force_range(w))) if fmap is not None else float(f)
            s = fmap.setting_for(applied, w) if fmap is not None else f
            m = squeeze(cfg, w, s, rig)
            out.append({"width_m": float(w), "requested_n": float(f), "applied_n": applied, "setting": s,
                        "measured_n": m, "rel_error": m / applied - 1.0})
    return out


def _yaml(key: str, value) -> str:
    return yaml.safe_dump({key: value}, default_flow_style=None, sort_keys=False, width=100)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("robot", help="robot folder name under sim/robots or a robot.yaml path")
    parser.add_argument("--commands", type=float, nargs="+", default=list(DEFAULT_COMMANDS))
    parser.add_argument("--tcp-offset", action="store_true", help="measure gripper.tcp_offset")
    parser.add_argument("--force", action="store_true", help="measure gripper.force_map")
    parser.add_argument("--check-force", action="store_true", help="requested vs measured pad force")
    parser.add_argument("--widths", type=float, nargs="+", help="block widths (m) for --force / --check-force")
    parser.add_argument("--settings", type=float, nargs="+", help="actuator settings for --force")
    parser.add_argument("--forces", type=float, nargs="+", default=[20.0, 60.0, 130.0, 235.0],
                        help="requested pad forces (N) for --check-force")
    args = parser.parse_args(argv)
    cfg = load_robot_config(args.robot, require_force_map=False)  # measuring the force map is what it is for
    # CLI output below: YAML / JSON on stdout.
    if args.tcp_offset:
        pairs = measure_tcp_offset(cfg, args.commands)
        print(_yaml("tcp_offset", [[round(w, 5), round(o, 5)] for w, o in pairs]))  # noqa: T201
    elif args.force:
        fm = measure_force_map(cfg, args.widths, args.settings)
        print(_yaml("force_map", {"widths": list(fm.widths), "settings": list(fm.settings),  # noqa: T201
                                  "pad_force": [list(r) for r in fm.pad_force], "max_force": list(fm.max_force)}))
    elif args.check_force:
        rows = check_force(cfg, args.forces, args.widths or default_widths(cfg, 3))
        print(json.dumps(rows, indent=1))  # noqa: T201
    else:
        pairs = measure_command_to_width(cfg, args.commands)
        print(_yaml("command_to_width", [[c, round(w, 5)] for c, w in pairs]))  # noqa: T201
        widths = np.array([w for _, w in pairs])
        cmds = np.array([c for c, _ in pairs])
        if np.any(np.diff(widths) * np.sign(np.diff(cmds)) * np.sign(cfg.gripper.closed_command -
                                                                     cfg.gripper.open_command) > 1e-6):
            raise SystemExit("measured widths are not monotone")


if __name__ == "__main__":
    main()
