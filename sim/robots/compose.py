"""Compose a robot from its config: arm + gripper attached with MjSpec, options merged, base placed, gravcomp.

:func:`robot_spec` is the one place a robot's MjSpec is made, for the world (:mod:`sim.world`), the IK and FK
models and the plan-time collision checker alike, so the robot is the same everywhere:

* a pre-combined ``mjcf`` is loaded as it is; otherwise ``gripper.mjcf``'s root body is attached at the arm's
  ``gripper.attach_site`` (names prefixed ``gripper.prefix``). ``attach()`` keeps only the parent's
  ``<option>`` (SIMULATION.md), so the two files' options are merged first (:func:`merge_options`): a setting
  only one file makes is kept, and where both set different values the gripper wins on contact settings
  (cone, impratio, noslip, ccd, override solref/solimp/margin/friction) and the arm on everything else;
* each file keeps its own ``<compiler>`` (angle units, ``autolimits``...): MjSpec converts every element with
  the compiler of the file it came from;
* keyframes are dropped (the home pose is ``arm.home``);
* ``gravcomp`` (when not None) sets every robot body's ``gravcomp`` to 1 or 0;
* ``base_pose`` moves every top-level element of the robot into one frame at that pose in the world;
* lights in the robot files are removed (with a warning): the scene lights the images, and a lamp on a
  robot would change every capture;
* the arm joints' ranges are set to ``arm.position_limits`` (which must lie inside the MJCF's ranges), so the
  IK, the simulated joints and the safety layer share one set of limits;
* ``gripper.define_tcp`` adds the TCP site a gripper file lacks (named ``arm.tcp_site``);
* ``gripper.servo_gain_scale`` scales the gripper's position-servo gains (:func:`scale_servo_gains`).

Units: m, rad; quaternions wxyz.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from torm.errors import SceneError

if TYPE_CHECKING:
    from sim.robots.config import RobotConfig

log = logging.getLogger(__name__)

#: Option fields a gripper file's value wins on when both files set them differently.
CONTACT_OPTIONS = ("cone", "impratio", "noslip_iterations", "noslip_tolerance", "ccd_iterations", "ccd_tolerance",
                   "o_margin", "o_solref", "o_solimp", "o_friction")
_FLAGS = ("enableflags", "disableflags")


def option_fields() -> list[str]:
    """The settable fields of ``MjSpec.option`` (MuJoCo version dependent)."""
    opt = mujoco.MjSpec().option
    out = []
    for name in dir(opt):
        if name.startswith("_") or callable(getattr(opt, name)):
            continue
        out.append(name)
    return out


def _same(a, b) -> bool:
    return bool(np.array_equal(np.asarray(a), np.asarray(b)))


def _set(opt, name: str, value) -> bool:
    try:
        setattr(opt, name, value.copy() if isinstance(value, np.ndarray) else value)
    except (AttributeError, TypeError):  # read-only in this MuJoCo version
        return False
    return True


def merge_options(parent, child, child_wins: tuple[str, ...] = CONTACT_OPTIONS) -> list[str]:
    """Merge ``child`` (an MjOption of a spec) into ``parent`` in place; return notes on the conflicts.

    A field only one side sets (differs from MuJoCo's default) takes that side's value; flag words are OR-ed;
    where both set different values ``child`` wins on ``child_wins`` and ``parent`` on the rest.
    """
    default = mujoco.MjSpec().option
    notes = []
    for name in option_fields():
        p, c, d = getattr(parent, name), getattr(child, name), getattr(default, name)
        if name in _FLAGS:
            _set(parent, name, int(p) | int(c))
            continue
        if _same(p, c) or _same(c, d):
            continue
        if _same(p, d) or name in child_wins:
            if not _same(p, d):
                notes.append(f"{name}: gripper {np.asarray(c).tolist()} over arm {np.asarray(p).tolist()}")
            _set(parent, name, c)
        else:
            notes.append(f"{name}: arm {np.asarray(p).tolist()} over gripper {np.asarray(c).tolist()}")
    return notes


def copy_options(dst, src) -> None:
    """Copy every option field of ``src`` into ``dst`` (both MjOption of specs)."""
    for name in option_fields():
        _set(dst, name, getattr(src, name))


def _load(path, what: str) -> mujoco.MjSpec:
    try:
        return mujoco.MjSpec.from_file(str(path))
    except ValueError as exc:
        raise SceneError(f"{what} {path} cannot be parsed: {exc}") from exc


def _drop_keyframes(spec: mujoco.MjSpec) -> None:
    for key in list(spec.keys):
        spec.delete(key)


def _root_body(spec: mujoco.MjSpec, name: str | None, where: str):
    if name:
        body = spec.body(name)
        if body is None:
            raise SceneError(f"{where}: no body {name!r} (gripper.root_body); bodies: "
                             f"{[b.name for b in spec.worldbody.bodies]}")
        return body
    tops = list(spec.worldbody.bodies)
    if len(tops) != 1:
        raise SceneError(f"{where} has {len(tops)} top-level bodies {[b.name for b in tops]}; name the one to "
                         "attach in gripper.root_body")
    return tops[0]


def attach_gripper(rcfg: RobotConfig) -> mujoco.MjSpec:
    """The arm spec with the gripper attached at ``rcfg.attach_site`` (names prefixed ``gripper.prefix``)."""
    arm = _load(rcfg.arm.mjcf, "arm.mjcf")
    grip = _load(rcfg.gripper.mjcf, "gripper.mjcf")
    site = arm.site(rcfg.attach_site)
    if site is None:
        raise SceneError(f"robot {rcfg.name!r}: arm.mjcf {rcfg.arm.mjcf} has no site {rcfg.attach_site!r} to attach "
                         f"the gripper at (gripper.attach_site); sites: {[s.name for s in arm.sites]}")
    for note in merge_options(arm.option, grip.option):
        log.info("robot %s options: %s", rcfg.name, note)
    copy_options(grip.option, arm.option)  # identical options: attach has nothing to warn about
    _drop_keyframes(arm)
    _drop_keyframes(grip)
    site.attach_body(_root_body(grip, rcfg.gripper.root_body, f"gripper.mjcf {rcfg.gripper.mjcf}"),
                     rcfg.gripper.prefix, "")
    arm.modelname = rcfg.name
    return arm


def place_base(spec: mujoco.MjSpec, pos, quat) -> None:
    """Move every top-level element of ``spec``'s worldbody into one frame at ``pos`` (m) / ``quat`` (wxyz)."""
    wb = spec.worldbody
    frame = wb.add_frame(pos=list(map(float, pos)), quat=list(map(float, quat)))
    elements = [*wb.bodies, *wb.geoms, *wb.sites, *wb.cameras, *wb.lights, *wb.frames]
    for el in elements:
        if el is not frame and el.frame is None:
            el.set_frame(frame)


def set_gravcomp(spec: mujoco.MjSpec, on: bool) -> int:
    """Set ``gravcomp`` of every body (world excluded) to 1 or 0; returns the number of bodies."""
    bodies = [b for b in spec.bodies if b.name != "world"]
    for b in bodies:
        b.gravcomp = 1.0 if on else 0.0
    return len(bodies)


_warned_lights: set[str] = set()


def strip_lights(spec: mujoco.MjSpec, where: str) -> int:
    """Delete every light of ``spec`` (warned once per ``where``); returns how many there were."""
    lights = list(spec.lights)
    for light in lights:
        spec.delete(light)
    if lights and where not in _warned_lights:
        _warned_lights.add(where)
        log.warning("%s: removed %d <light> element(s) from the robot files; the scene provides the lighting "
                    "(a lamp on the robot would change every captured image)", where, len(lights))
    return len(lights)


def apply_joint_limits(spec: mujoco.MjSpec, rcfg: RobotConfig) -> None:
    """Set the range of every arm joint to ``arm.position_limits`` (rad): one set of limits everywhere."""
    for name, (lo, hi) in zip(rcfg.arm.joints, rcfg.arm.position_limits, strict=True):
        joint = spec.joint(name)
        if joint is None:
            continue  # reported by RobotConfig.validate_against with the other missing names
        scale = 180.0 / np.pi if spec.compiler.degree and joint.type == mujoco.mjtJoint.mjJNT_HINGE else 1.0
        mlo, mhi = (float(v) / scale for v in joint.range)
        limited = joint.limited == mujoco.mjtLimited.mjLIMITED_TRUE or (
            joint.limited == mujoco.mjtLimited.mjLIMITED_AUTO and mlo < mhi)
        if limited and (lo < mlo - 1e-6 or hi > mhi + 1e-6):
            raise SceneError(f"robot {rcfg.name!r}: joint {name!r} limits [{lo}, {hi}] exceed the MJCF range "
                             f"[{mlo:.6g}, {mhi:.6g}] (rad); arm.position_limits must lie inside it")
        joint.range = [float(lo) * scale, float(hi) * scale]  # in the units of the file the joint came from
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE


def add_tcp_site(spec: mujoco.MjSpec, rcfg: RobotConfig) -> None:
    """Add ``gripper.define_tcp`` as a site named ``arm.tcp_site`` (SceneError naming the bodies if absent)."""
    d = rcfg.gripper.define_tcp
    if d is None:
        return
    body = spec.body(d.body)
    if body is None:
        raise SceneError(f"robot {rcfg.name!r}: gripper.define_tcp.body {d.body!r} is not a body of the composed "
                         f"model; bodies: {[b.name for b in spec.bodies if b.name and b.name != 'world']}")
    if spec.site(rcfg.arm.tcp_site) is not None:
        raise SceneError(f"robot {rcfg.name!r}: the model already has a site {rcfg.arm.tcp_site!r}; drop "
                         "gripper.define_tcp or name another arm.tcp_site")
    body.add_site(name=rcfg.arm.tcp_site, pos=list(map(float, d.pos)), quat=list(map(float, d.quat)),
                  size=[0.005, 0.005, 0.005], group=4)


def scale_servo_gains(spec: mujoco.MjSpec, rcfg: RobotConfig) -> None:
    """Multiply the gripper actuator's servo gains by ``gripper.servo_gain_scale`` s: ``gainprm[0]``, ``biasprm[0]``
    and ``biasprm[1]`` (the stiffness) by s, ``biasprm[2]`` (the damping) by sqrt(s), which keeps the damping ratio.
    The actuator is the one :meth:`RobotConfig.resolve` finds; ConfigError when it is not a position servo."""
    scale = float(rcfg.gripper.servo_gain_scale)
    if scale == 1.0:
        return
    from sim.robots.ids import _label, position_servo
    from torm.errors import ConfigError

    model = compile_spec(spec, f"robot {rcfg.name!r}")
    a = rcfg.resolve(model).gripper_actuator
    if not position_servo(model, a):
        raise ConfigError(f"robot {rcfg.name!r}: gripper.servo_gain_scale={scale:g} needs a position-servo gripper "
                          f"actuator (biastype affine with negative length feedback); {_label(model, a)} is not one: "
                          "remove servo_gain_scale")
    act = spec.actuators[a]
    gain, bias = list(act.gainprm), list(act.biasprm)
    gain[0] *= scale
    bias[0] *= scale
    bias[1] *= scale
    bias[2] *= float(np.sqrt(scale))
    act.gainprm, act.biasprm = gain, bias


def robot_spec(rcfg: RobotConfig) -> mujoco.MjSpec:
    """A fresh MjSpec of the robot alone: composed, keyframes and lights dropped, the arm's joint limits and a
    declared TCP site applied, gravcomp applied, base at ``base_pose``."""
    if rcfg.mjcf is not None:
        spec = _load(rcfg.mjcf, "mjcf")
        _drop_keyframes(spec)
    else:
        spec = attach_gripper(rcfg)
    strip_lights(spec, f"robot {rcfg.name!r}")
    apply_joint_limits(spec, rcfg)
    add_tcp_site(spec, rcfg)
    scale_servo_gains(spec, rcfg)
    if rcfg.gravcomp is not None:
        set_gravcomp(spec, rcfg.gravcomp)
    if not rcfg.base_pose.is_identity:
        place_base(spec, rcfg.base_pose.position, rcfg.base_pose.quat)
    return spec


def compile_spec(spec: mujoco.MjSpec, where: str) -> mujoco.MjModel:
    """``spec.compile()`` with a SceneError naming ``where`` when it fails."""
    try:
        return spec.compile()
    except ValueError as exc:
        raise SceneError(f"{where} does not compile: {exc}") from exc
