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
    from sim.robots.config import RobotConfig

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


def direct_drive(model: mujoco.MjModel, actuator: int) -> bool:
    """Whether the gripper ``actuator`` moves only slide joints (directly or through a tendon), so its force limit
    is the pad force; a hinge (a linkage) multiplies it by a width-dependent lever arm."""
    trn, tid = int(model.actuator_trntype[actuator]), int(model.actuator_trnid[actuator, 0])
    if trn in _JOINT_TRN:
        joints = {tid}
    elif trn == int(mujoco.mjtTrn.mjTRN_TENDON):
        joints = _tendon_joints(model, tid)
    else:
        return False
    return bool(joints) and all(int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_SLIDE) for j in joints)


def _body_geoms(model: mujoco.MjModel, bid: int) -> list[int]:
    return [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) == bid]


def _collides(model: mujoco.MjModel, g: int) -> bool:
    return bool(model.geom_contype[g] or model.geom_conaffinity[g])


def pad_candidates(model: mujoco.MjModel, prefix: str) -> list[str]:
    """Spellings of the collision geoms of the gripper's bodies (names starting with ``prefix``) for
    ``gripper.pad_geoms``: the geom name when it has one, else ``body:BODY#K``."""
    out = []
    for b in range(model.nbody):
        name = model.body(b).name
        if not name.startswith(prefix):
            continue
        for k, g in enumerate(_body_geoms(model, b)):
            if _collides(model, g):
                out.append(model.geom(g).name or f"body:{name}#{k}")
    return out


def resolve_pad(model: mujoco.MjModel, entry: str) -> list[int]:
    """Geom ids of one ``gripper.pad_geoms`` entry: a geom name, ``body:NAME`` (the body's collision geoms) or
    ``body:NAME#K`` (its K-th geom, 0-based); [] when it names nothing."""
    if not entry.startswith("body:"):
        g = int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, entry))
        return [g] if g >= 0 else []
    body, _, k = entry[len("body:"):].partition("#")
    bid = int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body))
    if bid < 0:
        return []
    geoms = _body_geoms(model, bid)
    if k:
        return [geoms[int(k)]] if k.isdigit() and int(k) < len(geoms) else []
    return [g for g in geoms if _collides(model, g)]


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


def position_servo(model: mujoco.MjModel, actuator: int) -> bool:
    """Whether ``actuator`` is a position servo: an affine bias with negative length feedback (force = gain x ctrl +
    b0 - kp x length - kv x velocity, MuJoCo's ``<position>`` or Menagerie's ``<general biastype="affine">``), so
    the force it presses with is kp x the position error, up to its force limit, not the limit itself."""
    return (int(model.actuator_biastype[actuator]) == int(mujoco.mjtBias.mjBIAS_AFFINE)
            and float(model.actuator_biasprm[actuator, 1]) < 0.0)


def servo_pull_n(model: mujoco.MjModel, actuator: int, finger_joints: tuple[int, ...], closed_command: float) -> float:
    """Force (actuator units, N for a slide or tendon drive) the position servo ``actuator`` pulls with when
    commanded closed while its fingers stand half-way (each finger joint at the middle of its range): the static
    part of MuJoCo's affine actuator force, gain x ctrl + b0 + b1 x length (velocity 0), before the force limit."""
    d = mujoco.MjData(model)
    for j in finger_joints:
        if model.jnt_limited[j]:
            d.qpos[model.jnt_qposadr[j]] = float(np.mean(model.jnt_range[j]))
    mujoco.mj_fwdPosition(model, d)
    g, b = model.actuator_gainprm[actuator], model.actuator_biasprm[actuator]
    return abs(float(g[0]) * float(closed_command) + float(b[0]) + float(b[1]) * float(d.actuator_length[actuator]))


def force_map_problem(model: mujoco.MjModel, rcfg: RobotConfig, ids: RobotIds) -> str | None:
    """Why ``rcfg`` needs a ``gripper.force_map`` it lacks (its actuator is a linkage, or a position servo on slide
    fingers whose force limit is not what the pads press with), or None."""
    a = ids.gripper_actuator
    if rcfg.gripper.force_map is not None or a < 0:
        return None
    if direct_drive(model, a):
        if not position_servo(model, a):
            return None
        pull = servo_pull_n(model, a, ids.gripper_joints, rcfg.gripper.closed_command)
        limit = float(model.actuator_forcerange[a, 1]) if model.actuator_forcelimited[a] else float("inf")
        if pull >= limit:
            return None  # the servo pulls harder than its limit even half-way closed: the limit is what it presses
        return (f"robot {rcfg.name!r}: gripper actuator {_label(model, a)} is a position servo that pulls only "
                f"{pull:.3g} N half-way closed (force = {-float(model.actuator_biasprm[a, 1]):g} x position error; "
                f"its force limit {limit:g} never binds), so its pads press far less than a grip asks; measure what "
                f"it squeezes with python -m sim.robots.measure_gripper {rcfg.name} --force and paste it into "
                "gripper.force_map (max_force: the most per width), or raise its gain with gripper.servo_gain_scale")
    return (f"robot {rcfg.name!r}: gripper actuator {_label(model, a)} drives a hinge (a linkage), so its force limit "
            "is not the pad force and a grip would be recorded with the wrong force; measure a force map with "
            f"python -m sim.robots.measure_gripper {rcfg.name} --force (the robot's folder name or the path of its "
            "YAML) and paste it into gripper.force_map")


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
    def pads(entries: tuple[str, ...]) -> list[int]:
        out: list[int] = []
        for e in entries:
            found = resolve_pad(model, e)
            if not found:
                hint = ""
                if not e.startswith("body:") and mujoco.mj_name2id(model, G, pre + e) >= 0:
                    hint = f" (the composed model calls it {pre + e!r}: gripper names carry gripper.prefix)"
                problems.append(f"pad geom {e!r}{hint} (candidates: {', '.join(pad_candidates(model, pre)) or 'none'}; "
                                "an unnamed geom is named body:BODY or body:BODY#K)")
            out += found
        return out

    left = pads(grip.left_pads)
    right = pads(grip.right_pads)
    if set(left) & set(right):
        problems.append(f"pad geoms {sorted(set(left) & set(right))} are listed for both fingers")
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
        if jid >= 0 and model.jnt_limited[jid]:  # the composed model carries the YAML's limits: a model from
            mlo, mhi = model.jnt_range[jid]      # elsewhere may not
            if lo < mlo - 1e-6 or hi > mhi + 1e-6:
                problems.append(f"joint {j!r} limits [{lo}, {hi}] exceed the MJCF range [{mlo}, {mhi}] (rad)")
    if problems:
        return None, problems
    ids = RobotIds(arm_joints=np.array(arm_j), arm_qadr=np.array([model.jnt_qposadr[j] for j in arm_j]),
                   arm_dadr=np.array([model.jnt_dofadr[j] for j in arm_j]), arm_actuators=np.array(arm_a),
                   gripper_actuator=int(g_act), gripper_joints=tuple(grip_j), tcp_site=tcp, flange_site=flange,
                   left_pads=tuple(left), right_pads=tuple(right))
    return ids, []
