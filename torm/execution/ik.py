"""Inverse kinematics with mink on a robot-only MuJoCo model.

The IK model holds the robot alone (no free object bodies: they enlarge the QP). mink raises
nothing for an unreachable target and just stops short, so :meth:`IKSolver.solve` checks the final
residual and reports it; :class:`UnreachableError` is raised by callers that require convergence.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import mink
import mujoco
import numpy as np

from torm.config import Range, check_finite
from torm.errors import ConfigError, ExecutionError

#: Random restarts of :meth:`IKSolver.solve_free` after the seeded solve failed.
RESTARTS = 8


class UnreachableError(ExecutionError):
    """No joint configuration within the limits puts the TCP at the requested pose."""


#: IK solutions stay this far inside every joint range (rad): the safety layer refuses a joint beyond its limit by
#: any amount, and the QP's integration step may overshoot a bound it approaches by a fraction of a mrad.
IK_LIMIT_MARGIN_RAD = 2e-3


@dataclass(frozen=True)
class IKConfig:
    """IK settings. Tolerances in m and rad; ``dt`` is the integration step of the velocity QP (s)."""

    pos_tol: float = 1e-3
    rot_tol: float = 1e-2
    max_iters: Annotated[int, Range(1, 2000, "10x the default; 0.17 ms per iteration: a failed solve < 0.5 s")] = 200
    dt: float = 0.05
    damping: float = 1e-3
    lm_damping: float = 1e-3
    posture_cost: float = 1e-2
    solver: str = "daqp"

    def __post_init__(self) -> None:
        check_finite(self, "IKConfig")  # ranges and NaN / inf (torm.config), also when built in Python
        if self.pos_tol <= 0 or self.rot_tol <= 0 or self.dt <= 0 or self.max_iters < 1:
            raise ConfigError("IKConfig: tolerances, dt and max_iters must be positive")


@dataclass(frozen=True)
class IKResult:
    """Arm joints ``q`` (n,) rad, residual position (m) / rotation (rad) errors, and whether both are in tolerance."""

    q: np.ndarray
    pos_err: float
    rot_err: float
    converged: bool
    iters: int


class IKSolver:
    """Solve for arm joints that put ``tcp_site`` at a world pose.

    Args:
        model: a MuJoCo model of the robot alone, base at the world origin.
        joint_names: the arm joints solved for, in order; other joints stay at their initial values.
        tcp_site: the site whose pose is controlled.
        config: tolerances and solver settings.
    """

    def __init__(self, model: mujoco.MjModel, joint_names: tuple[str, ...], tcp_site: str,
                 config: IKConfig | None = None) -> None:
        self.model = model
        self.config = config or IKConfig()
        self.joint_names = tuple(joint_names)
        missing = [j for j in self.joint_names if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) < 0]
        if missing:
            raise ConfigError(f"IK model has no joint(s) {missing}")
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, tcp_site) < 0:
            raise ConfigError(f"IK model has no site {tcp_site!r}")
        self.tcp_site = tcp_site
        self._qadr = np.array([model.jnt_qposadr[model.joint(j).id] for j in self.joint_names])
        self.configuration = mink.Configuration(model)
        self._frame = mink.FrameTask(tcp_site, "site", position_cost=1.0, orientation_cost=1.0,
                                     lm_damping=self.config.lm_damping)
        self._posture = mink.PostureTask(model, cost=self.config.posture_cost)
        # IK keeps IK_LIMIT_MARGIN_RAD inside every joint range, so a solution never lands on a limit that the
        # safety layer checks exactly (a float step past it refused a lift: -2.8902 rad against -2.8900)
        self._limits = [mink.ConfigurationLimit(model, min_distance_from_limits=IK_LIMIT_MARGIN_RAD)]

    def forward(self, q_arm: np.ndarray) -> np.ndarray:
        """TCP pose (4, 4) in the world for arm joints ``q_arm`` (n,) rad."""
        q = self.configuration.q.copy()
        q[self._qadr] = q_arm
        self.configuration.update(q)
        return self.configuration.get_transform_frame_to_world(self.tcp_site, "site").as_matrix()

    def solve(self, T_world_tcp: np.ndarray, q_init: np.ndarray, q_posture: np.ndarray | None = None) -> IKResult:
        """Joints reaching ``T_world_tcp`` (4, 4), starting from ``q_init`` (n,) rad; never raises for unreachable."""
        cfg = self.config
        q = self.configuration.q.copy()
        q[self._qadr] = q_init
        self.configuration.update(q)
        q_post = q.copy()
        if q_posture is not None:
            q_post[self._qadr] = q_posture
        self._posture.set_target(q_post)
        self._frame.set_target(mink.SE3.from_matrix(np.asarray(T_world_tcp, float)))
        pos_err = rot_err = np.inf
        it = 0
        while it < cfg.max_iters:
            it += 1
            vel = mink.solve_ik(self.configuration, [self._frame, self._posture], cfg.dt, cfg.solver,
                                damping=cfg.damping, limits=self._limits)
            self.configuration.integrate_inplace(vel, cfg.dt)
            err = self._frame.compute_error(self.configuration)
            pos_err, rot_err = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
            if not np.all(np.isfinite(err)):
                break
            if pos_err < cfg.pos_tol and rot_err < cfg.rot_tol:
                break
        q_out = self.configuration.q[self._qadr].copy()
        lo, hi = self.joint_ranges(unlimited=np.inf)
        inside = np.clip(q_out, lo + 0.5 * IK_LIMIT_MARGIN_RAD, hi - 0.5 * IK_LIMIT_MARGIN_RAD)
        if not np.array_equal(inside, q_out):  # the QP's integration stepped into the margin: back inside, re-measured
            q_out = inside
            q[self._qadr] = q_out
            self.configuration.update(q)
            err = self._frame.compute_error(self.configuration)
            pos_err, rot_err = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
        ok = bool(np.isfinite(pos_err) and pos_err < cfg.pos_tol and rot_err < cfg.rot_tol)
        return IKResult(q_out, pos_err, rot_err, ok, it)

    def joint_ranges(self, unlimited: float = np.pi) -> tuple[np.ndarray, np.ndarray]:
        """(lower (n,), upper (n,)) rad of the solved joints: the model's ranges, which the robot composition sets
        to the robot config's ``arm.position_limits`` (one set of limits for IK and the safety layer);
        unlimited joints get [-unlimited, unlimited] (pi: for sampling)."""
        lo, hi = np.full(len(self.joint_names), -unlimited), np.full(len(self.joint_names), unlimited)
        for k, j in enumerate(self.joint_names):
            jid = self.model.joint(j).id
            if self.model.jnt_limited[jid]:
                lo[k], hi[k] = self.model.jnt_range[jid]
        return lo, hi

    def solve_free(self, T_world_tcp: np.ndarray, q_seed: np.ndarray, restarts: int = RESTARTS,
                   seed: int = 0) -> IKResult:
        """The solve of a free-move target used by execution and by the start-up reach check alike.

        From ``q_seed`` (n,) rad with the posture task at ``q_seed``; a solve that stalls within 2 cm is polished
        once with the posture at its own result; when that fails too, up to ``restarts`` further solves start from
        joint configurations drawn uniformly within :meth:`joint_ranges` (a generator seeded with ``seed``, so the
        result is deterministic). Returns the first converged result, else the one with the smallest residual.
        """
        res = self.solve(T_world_tcp, q_seed, q_posture=q_seed)
        if not res.converged and res.pos_err < 0.02:
            res = self.solve(T_world_tcp, res.q, q_posture=res.q)
        if res.converged or restarts <= 0:
            return res
        best = res
        lo, hi = self.joint_ranges()
        rng = np.random.default_rng(seed)
        for _ in range(restarts):
            q0 = rng.uniform(lo, hi)
            r = self.solve(T_world_tcp, q0, q_posture=q0)
            if not r.converged and r.pos_err < 0.02:
                r = self.solve(T_world_tcp, r.q, q_posture=r.q)
            if r.converged:
                return r
            if r.pos_err < best.pos_err:
                best = r
        return best

    def solve_or_raise(self, T_world_tcp: np.ndarray, q_init: np.ndarray, what: str = "target") -> np.ndarray:
        """Like :meth:`solve` but raise :class:`UnreachableError` naming ``what`` and the residual."""
        res = self.solve(T_world_tcp, q_init)
        if not res.converged:
            p = np.round(np.asarray(T_world_tcp)[:3, 3], 4).tolist()
            raise UnreachableError(
                f"{what} at {p} m is unreachable: IK residual {res.pos_err * 1000:.1f} mm / "
                f"{np.degrees(res.rot_err):.1f} deg after {res.iters} iterations"
            )
        return res.q
