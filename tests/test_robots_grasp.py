"""Key physics check: the full simulated arm grasps a glass cylinder off the table and lifts it 25 cm.

Joint targets are scripted with a small damped-least-squares IK on the arm (TCP pointing down,
closing along world y), streamed to the position actuators every physics step.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np
import pytest

from sim.robots.config import RobotConfig, load_robot_config

SCENE = """
<mujoco model="glass grasp test">
  <option cone="elliptic" impratio="10" timestep="0.002" integrator="implicitfast">
    <flag multiccd="enable"/>
  </option>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true"/>
    <geom name="table" type="plane" size="1 1 0.05" rgba="0.8 0.8 0.8 1"/>
    <!-- Thin-walled glass cylinder: r 0.03 m, h 0.10 m, 0.2 kg (a solid one would be 0.71 kg). -->
    <body name="glass" pos="0.5 0 0.05">
      <freejoint/>
      <geom name="glass" type="cylinder" size="0.03 0.05" mass="0.2" friction="0.5 0.005 0.0001"
        rgba="0.7 0.9 1 0.3"/>
    </body>
  </worldbody>
</mujoco>
"""
DOWN = np.column_stack([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])  # TCP axes in world: approach -z, close y
GRASP_Z = 0.06  # TCP height at the grasp (m); the glass spans z 0..0.10
LIFT = 0.25


class Rig:
    """The robot attached into SCENE, with IK and scripted joint-target streaming."""

    def __init__(self, cfg: RobotConfig, grip_force: float | None = None) -> None:
        spec = mujoco.MjSpec.from_string(SCENE)
        robot = mujoco.MjSpec.from_file(str(cfg.mjcf))
        spec.worldbody.add_frame().attach_body(robot.body("base"), "robot/", "")
        self.model = spec.compile()
        m = self.model
        assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 10
        assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_MULTICCD
        self.cfg = cfg
        self.data = mujoco.MjData(m)
        self.qadr = np.array([m.joint("robot/" + j).qposadr[0] for j in cfg.arm.joints])
        self.dadr = np.array([m.joint("robot/" + j).dofadr[0] for j in cfg.arm.joints])
        self.arm_act = np.array([m.actuator("robot/" + a).id for a in cfg.arm.actuators])
        self.grip_act = m.actuator("robot/" + cfg.gripper.actuator).id
        self.tcp = m.site("robot/" + cfg.arm.tcp_site).id
        if grip_force is not None:
            m.actuator_forcerange[self.grip_act] = (-grip_force, grip_force)
        self.data.qpos[self.qadr] = cfg.arm.home_q
        self.data.ctrl[self.arm_act] = cfg.arm.home_q
        mujoco.mj_forward(m, self.data)

    def ik(self, pos: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Arm joints (rad) putting the TCP at ``pos`` (m) with orientation DOWN; asserts convergence."""
        m = self.model
        d = mujoco.MjData(m)
        d.qpos[:] = m.qpos0
        q = q0.copy()
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        err = np.inf
        for _ in range(100):
            d.qpos[self.qadr] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            R = d.site_xmat[self.tcp].reshape(3, 3)
            e = np.r_[pos - d.site_xpos[self.tcp], 0.5 * sum(np.cross(R[:, i], DOWN[:, i]) for i in range(3))]
            err = np.linalg.norm(e)
            if err < 1e-9:
                break
            mujoco.mj_jacSite(m, d, jp, jr, self.tcp)
            J = np.r_[jp, jr][:, self.dadr]
            q = q + J.T @ np.linalg.solve(J @ J.T + 1e-6 * np.eye(6), e)
        assert err < 1e-6, err
        assert np.all(q >= self.cfg.arm.lower) and np.all(q <= self.cfg.arm.upper)
        return q

    def line(self, p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, n: int = 15) -> np.ndarray:
        """(n, 6) IK solutions along the straight TCP segment p0 -> p1."""
        qs, q = [], q0
        for s in np.linspace(0.0, 1.0, n):
            q = self.ik(p0 + s * (p1 - p0), q)
            qs.append(q)
        return np.array(qs)

    def run(self, qs: np.ndarray, duration: float, grip: float | Callable[[float], float]) -> None:
        """Stream joint targets linearly interpolated along ``qs`` over ``duration`` s."""
        qs = np.atleast_2d(qs)
        n = int(round(duration / self.model.opt.timestep))
        for k in range(n):
            s = (k + 1) / n * (len(qs) - 1)
            i = min(int(s), max(len(qs) - 2, 0))
            f = s - i
            self.data.ctrl[self.arm_act] = qs[i] if len(qs) == 1 else qs[i] * (1 - f) + qs[i + 1] * f
            self.data.ctrl[self.grip_act] = grip(k / n) if callable(grip) else grip
            mujoco.mj_step(self.model, self.data)

    def glass_in_tcp(self) -> np.ndarray:
        """Glass position in the TCP frame (m)."""
        R = self.data.site_xmat[self.tcp].reshape(3, 3)
        return R.T @ (self.data.body("glass").xpos - self.data.site_xpos[self.tcp])


def pick_and_lift(grip_force: float | None = None) -> tuple[float, float, Rig]:
    """Approach, descend, close (command 255), lift 25 cm; returns (glass rise m, slip m, rig)."""
    rig = Rig(load_robot_config("inovo_2f85"), grip_force)
    home = rig.cfg.arm.home_q
    above = np.array([0.5, 0.0, GRASP_Z + 0.15])
    at = np.array([0.5, 0.0, GRASP_Z])
    top = at + [0.0, 0.0, LIFT]
    rig.run(home, 0.2, 0)
    q_above = rig.ik(above, home)
    rig.run(np.array([home, q_above]), 1.0, 0)
    down = rig.line(above, at, q_above)
    rig.run(down, 1.0, 0)
    rig.run(down[-1], 0.2, 0)
    assert np.linalg.norm(rig.data.site_xpos[rig.tcp] - at) < 2e-3  # the arm tracks its targets
    rig.run(down[-1], 0.5, lambda s: 255 * s)
    rig.run(down[-1], 0.4, 255)
    z0, rel0 = rig.data.body("glass").xpos[2], rig.glass_in_tcp()
    rig.run(rig.line(at, top, down[-1]), 1.5, 255)
    rig.run(rig.line(top, top, down[-1]), 0.5, 255)
    rise = rig.data.body("glass").xpos[2] - z0
    slip = float(np.linalg.norm(rig.glass_in_tcp() - rel0))
    assert all(int(w.number) == 0 for w in rig.data.warning)
    return rise, slip, rig


@pytest.mark.slow
def test_glass_cylinder_stays_in_gripper_through_25cm_lift() -> None:
    rise, slip, rig = pick_and_lift()
    assert rise >= 0.24, rise
    assert slip < 0.005, slip
    # The pads hold it (both pads in contact with the glass).
    glass = rig.model.geom("glass").id
    g = rig.cfg.gripper
    pads = {rig.model.geom("robot/" + n).id for n in g.left_pads + g.right_pads}
    touching = {c.geom1 if c.geom2 == glass else c.geom2 for c in rig.data.contact[: rig.data.ncon]
                if glass in (c.geom1, c.geom2)}
    assert pads <= touching


@pytest.mark.slow
def test_weak_grip_drops_the_glass() -> None:
    """Negative control: the same script with a 1 N grip cannot lift it (the check can fail)."""
    rise, slip, _ = pick_and_lift(grip_force=1.0)
    assert rise < 0.05 or slip > 0.05
