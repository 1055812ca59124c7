"""Measure a gripper's command -> pad-gap map in simulation (nothing between the pads).

Run ``python -m sim.robots.measure_gripper inovo_2f85`` to print the ``command_to_width`` pairs for a
robot.yaml. Units: m, s. The gap is the signed distance between the two pad collision geoms
(``mj_geomDistance``), so it is exact for any pad shape.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence

import mujoco
import numpy as np

from sim.robot_config import RobotConfig, load_robot_config

DEFAULT_COMMANDS = (0, 32, 64, 96, 128, 160, 192, 224, 255)


def pad_gap(model: mujoco.MjModel, data: mujoco.MjData, pad_geoms: Sequence[str]) -> float:
    """Signed distance (m) between the two pad geoms in ``data`` (negative = interpenetrating)."""
    g1, g2 = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in pad_geoms)
    return float(mujoco.mj_geomDistance(model, data, g1, g2, 1.0, None))


def settle_gripper(model: mujoco.MjModel, data: mujoco.MjData, cfg: RobotConfig, command: float,
                   duration_s: float = 1.0) -> float:
    """Hold the arm at its home pose, command the gripper, step ``duration_s`` and return the pad gap (m)."""
    arm_act = [model.actuator(n).id for n in cfg.arm.actuators]
    data.ctrl[arm_act] = cfg.arm.home_q
    data.ctrl[model.actuator(cfg.gripper.actuator).id] = command
    for _ in range(int(round(duration_s / model.opt.timestep))):
        mujoco.mj_step(model, data)
    return pad_gap(model, data, cfg.gripper.pad_geoms)


def measure_command_to_width(cfg: RobotConfig, commands: Sequence[float] = DEFAULT_COMMANDS,
                             duration_s: float = 1.0) -> list[tuple[float, float]]:
    """[(command, settled pad gap m)] for each command, starting open at the home pose each time."""
    model = mujoco.MjModel.from_xml_path(str(cfg.scene))
    out = []
    for cmd in commands:
        data = mujoco.MjData(model)
        data.qpos[[model.joint(n).qposadr[0] for n in cfg.arm.joints]] = cfg.arm.home_q
        mujoco.mj_forward(model, data)
        out.append((float(cmd), settle_gripper(model, data, cfg, cmd, duration_s)))
    return out


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("robot", help="robot folder name under sim/robots or a robot.yaml path")
    parser.add_argument("--commands", type=float, nargs="+", default=list(DEFAULT_COMMANDS))
    args = parser.parse_args(argv)
    cfg = load_robot_config(args.robot)
    pairs = measure_command_to_width(cfg, args.commands)
    print(json.dumps([[c, round(w, 5)] for c, w in pairs]))  # noqa: T201 - CLI output
    widths = np.array([w for _, w in pairs])
    if np.any(np.diff(widths) > 1e-6):
        raise SystemExit("measured widths are not monotone")


if __name__ == "__main__":
    main()
