"""Resolve the names in a robot config to ids in a compiled model (robot-only model or a whole world).

Everything that addresses the robot in a MuJoCo model goes through :class:`RobotIds`, so the rules live in one
place: names are those of the composed model (gripper elements carry ``gripper.prefix``; a missing name that
exists with the prefix is reported with that hint); an actuator left unnamed (``arm.actuators`` omitted or with
null entries, ``gripper.actuator`` omitted) is the one whose transmission is that joint (or, for the gripper, a
tendon through one of its joints).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from torm.errors import SceneError

if TYPE_CHECKING:
    from sim.robot_config import RobotConfig

_JOINT_TRN = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))


def _joint_actuators(model: mujoco.MjModel, jid: int) -> list[int]:
    return [a for a in range(model.nu) if int(model.actuator_trntype[a]) in _JOINT_TRN
            and int(model.actuator_trnid[a, 0]) == jid]


def _tendon_joints(model: mujoco.MjModel, tid: int) -> set[int]:
    adr, num = int(model.tendon_adr[tid]), int(model.tendon_num[tid])
    return {int(model.wrap_objid[w]) for w in range(adr, adr + num)
            if int(model.wrap_type[w]) == int(mujoco.mjtWrap.mjWRAP_JOINT)}


def _gripper_actuator_candidates(model: mujoco.MjModel, joint_ids: set[int]) -> list[int]:
    out = []
    for a in range(model.nu):
        trn, tid = int(model.actuator_trntype[a]), int(model.actuator_trnid[a, 0])
        direct = trn in _JOINT_TRN and tid in joint_ids
        if direct or (trn == int(mujoco.mjtTrn.mjTRN_TENDON) and _tendon_joints(model, tid) & joint_ids):
            out.append(a)
    return out


def _label(model: mujoco.MjModel, a: int) -> str:
    return repr(model.actuator(a).name) if model.actuator(a).name else f"#{a} (unnamed)"


def _count(model: mujoco.MjModel, found: list[int]) -> str:
    return "no actuator" if not found else f"{len(found)} actuators ({', '.join(_label(model, x) for x in found)})"


@dataclass(frozen=True)
class RobotIds:
    """Ids of the robot's parts in one compiled model.

    Attributes:
        arm_joints: (n,) arm joint ids; ``arm_qadr`` / ``arm_dadr`` their qpos / dof addresses.
        arm_actuators: (n,) actuator ids driving the arm joints, same order.
        gripper_actuator: the gripper actuator id.
        gripper_joints: finger joint ids.
        tcp_site, flange_site: site ids.
        left_pads, right_pads: pad geom ids of each finger.
    """

    arm_joints: np.ndarray
    arm_qadr: np.ndarray
    arm_dadr: np.ndarray
    arm_actuators: np.ndarray
    gripper_actuator: int
    gripper_joints: tuple[int, ...]
    tcp_site: int
    flange_site: int
    left_pads: tuple[int, ...]
    right_pads: tuple[int, ...]

    @property
    def pads(self) -> tuple[int, ...]:
        return self.left_pads + self.right_pads

    @classmethod
    def resolve(cls, model: mujoco.MjModel, rcfg: RobotConfig) -> RobotIds:
        """Resolve ``rcfg``'s names in ``model``; SceneError naming every missing or inconsistent part."""
        ids, problems = _resolve(model, rcfg)
        if problems:
            raise SceneError(f"robot {rcfg.name!r} does not match the compiled model: missing or inconsistent "
                             f"{', '.join(problems)}; fix the names in its robot.yaml or the MJCF")
        return ids  # type: ignore[return-value]


def problems_in(model: mujoco.MjModel, rcfg: RobotConfig) -> list[str]:
    """Descriptions of everything ``rcfg`` names that ``model`` lacks or contradicts (empty = consistent)."""
    return _resolve(model, rcfg)[1]


def _resolve(model: mujoco.MjModel, rcfg: RobotConfig) -> tuple[RobotIds | None, list[str]]:
    arm, grip = rcfg.arm, rcfg.gripper
    pre = grip.prefix
    J, A, S, G = (mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_ACTUATOR, mujoco.mjtObj.mjOBJ_SITE,
                  mujoco.mjtObj.mjOBJ_GEOM)
    problems: list[str] = []

    def need(obj: mujoco.mjtObj, kind: str, name: str, prefix: str = "") -> int:
        i = int(mujoco.mj_name2id(model, obj, name))
        if i < 0:
            hint = ""
            if prefix and mujoco.mj_name2id(model, obj, prefix + name) >= 0:
                hint = f" (the composed model calls it {prefix + name!r}: gripper names carry gripper.prefix)"
            problems.append(f"{kind} {name!r}{hint}")
        return i

    arm_j = [need(J, "joint", j) for j in arm.joints]
    grip_j = [need(J, "joint", j, pre) for j in grip.joints]
    tcp = need(S, "site", arm.tcp_site, pre)
    flange = need(S, "site", arm.flange_site)
    left = [need(G, "geom", g, pre) for g in grip.left_pads]
    right = [need(G, "geom", g, pre) for g in grip.right_pads]
    arm_a: list[int] = []
    for j, jid, a in zip(arm.joints, arm_j, arm.actuator_names, strict=True):
        if a:
            aid = need(A, "actuator", a)
            if aid >= 0 and jid >= 0 and (int(model.actuator_trntype[aid]) not in _JOINT_TRN
                                          or int(model.actuator_trnid[aid, 0]) != jid):
                problems.append(f"actuator {a!r} does not drive joint {j!r} (arm.actuators must follow arm.joints)")
        elif jid >= 0:
            found = _joint_actuators(model, jid)
            if len(found) != 1:
                problems.append(f"{_count(model, found)} driving joint {j!r}; name the one to use in arm.actuators")
            aid = found[0] if found else -1
        else:
            aid = -1
        arm_a.append(aid)
    if grip.actuator:
        g_act = need(A, "actuator", grip.actuator, pre)
    elif all(j >= 0 for j in grip_j):
        found = [a for a in _gripper_actuator_candidates(model, set(grip_j)) if a not in arm_a]
        if len(found) != 1:
            problems.append(f"{_count(model, found)} driving the gripper joints {list(grip.joints)}; name the one "
                            "to use in gripper.actuator")
        g_act = found[0] if found else -1
    else:
        g_act = -1
    for j, jid, (lo, hi) in zip(arm.joints, arm_j, arm.position_limits, strict=True):
        if jid >= 0 and model.jnt_limited[jid]:
            mlo, mhi = model.jnt_range[jid]
            if lo < mlo - 1e-9 or hi > mhi + 1e-9:
                problems.append(f"joint {j!r} limits [{lo}, {hi}] exceed the MJCF range [{mlo}, {mhi}] (rad)")
    if problems:
        return None, problems
    ids = RobotIds(arm_joints=np.array(arm_j), arm_qadr=np.array([model.jnt_qposadr[j] for j in arm_j]),
                   arm_dadr=np.array([model.jnt_dofadr[j] for j in arm_j]), arm_actuators=np.array(arm_a),
                   gripper_actuator=int(g_act), gripper_joints=tuple(grip_j), tcp_site=tcp, flange_site=flange,
                   left_pads=tuple(left), right_pads=tuple(right))
    return ids, []
