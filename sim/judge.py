"""The judge: scores a simulated trial from the physics afterwards, as an observer scores a real one.

The decision loop (``torm/loop.py``) never sees ground truth; it attempts every object it believes in. The judge
holds the simulator's truth and watches: it hears when each pick phase starts and ends
(:class:`torm.execution.observer.PickObserver`), samples the true object and TCP positions on every control step
of the carrying phases, and decides what each attempt did:

- **target**: the real object that rose during the lift (more than :attr:`PickJudge.rise_threshold`); else the
  real object whose bounding box (world axes, at rest) lies within :attr:`PickJudge.target_radius` of the grasp
  centre (a miss on it); else
  none: the attempt was at something that is not there, a ``phantom_attempt``;
- **outcome** on the target: ``collision_on_approach`` when the target (or a neighbour) moved before the fingers
  closed, else the paper's success test (:func:`torm.execution.success.judge_pick`) on the sampled trace;
- **disturbed**: how far every other object moved (m), for phantom attempts too.

:class:`TrialJudge` adds the trial-level view: which reconstruction matches which real object (reporting only),
reconstruction metrics against the true meshes, one row per real object, one per attempt, and the spurious
reconstructions with what their attempts did. Units: m, s; world frame.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Any

import numpy as np

from torm.execution.pick_config import PickConfig
from torm.execution.success import Outcome, PickTrace, SuccessCriteria, judge_pick
from torm.types import Grasp, ObjectPointCloud

log = logging.getLogger(__name__)

#: Loop outcomes that mean no motion happened or the motion was cut by an error: the judge keeps them.
_PASS_THROUGH = (Outcome.NO_GRASP, Outcome.UNREACHABLE, Outcome.PHYSICS, Outcome.SAFETY_STOP, Outcome.OTHER)


class PickJudge:
    """Scores picks on a simulated backend from the true object poses (see the module docstring).

    Args:
        backend: the full :class:`sim.backend.SimBackend` (ground truth, step callbacks).
        criteria: the success test's tolerances.
        pick: the pick settings whose ``approach_tolerance``, ``neighbour_tolerance`` and ``sample_dt`` apply.
        rise_threshold: an object that rose more than this during the lift was the attempt's target (m).
        target_radius: with nothing lifted, the real object whose bounding box is this close to the grasp centre (m).

    Attributes:
        verdicts: ``id(loop PickResult) -> judged PickResult`` for every attempt watched.
        handled: objects an earlier attempt acted on (left out of later neighbour checks: a released ball may roll).
    """

    def __init__(self, backend: Any, criteria: SuccessCriteria | None = None, pick: PickConfig | None = None,
                 rise_threshold: float = 0.05, target_radius: float = 0.02) -> None:
        self.backend, self.gt = backend, backend.ground_truth
        self.criteria, self.pick = criteria or SuccessCriteria(), pick or PickConfig()
        self.rise_threshold, self.target_radius = rise_threshold, target_radius
        self.verdicts: dict[int, Any] = {}
        self.handled: set[int] = set()
        self._a: dict[str, Any] = {}
        self._sampling: str | None = None
        self._next = -np.inf
        self._cb = backend.add_step_callback(self._on_step) if hasattr(backend, "add_step_callback") else None

    # -- observation ----------------------------------------------------------------------------------------
    def _positions(self) -> dict[int, np.ndarray]:
        return {k: T[:3, 3].copy() for k, T in self.gt.object_poses().items()}

    def _tcp(self) -> np.ndarray:
        return np.asarray(self.backend.arm.state().T_world_tcp[:3, 3], float).copy()

    def _rel(self) -> dict[int, np.ndarray]:
        tcp = self._tcp()
        return {k: p - tcp for k, p in self._positions().items()}

    def _on_step(self, t: float) -> None:
        if self._sampling is not None and t >= self._next:
            self._a[self._sampling].append(self._rel())
            self._next = t + self.pick.sample_dt

    def attempt_started(self, grasp: Grasp) -> None:
        self._a = {"grasp": grasp, "rest": self._positions(), "lift": [], "translate": [],
                   "surfaces": self.gt.object_meshes()}

    def phase_started(self, name: str) -> None:
        if name == "lift":
            self._a["tcp_rest"] = self._tcp()
        if name in ("lift", "translate"):
            self._a[name].append(self._rel())
            self._sampling, self._next = name, -np.inf

    def phase_ended(self, name: str) -> None:
        if name == "approach":
            self._a["before_close"] = self._positions()
        if name in ("lift", "translate"):
            self._a[name].append(self._rel())
            self._sampling = None
            self._a[f"{name}_end"] = self._positions()
            self._a[f"tcp_{name}_end"] = self._tcp()

    def attempt_ended(self, result: Any) -> None:
        self._sampling = None
        self._a["final"] = self._positions()
        self.verdicts[id(result)] = self._verdict(result)
        self._a = {}

    def close(self) -> None:
        """Stop watching (removes the step callback)."""
        if self._cb is not None:
            self.backend.remove_step_callback(self._cb)
            self._cb = None

    # -- verdict --------------------------------------------------------------------------------------------
    def _target(self, a: dict[str, Any]) -> tuple[int | None, str]:
        rest = a["rest"]
        if "lift_end" in a:
            rise = {k: float(a["lift_end"][k][2] - p[2]) for k, p in rest.items()}
            k = max(rise, key=rise.get, default=None)
            if k is not None and rise[k] > self.rise_threshold:
                return k, f"object {k} rose {rise[k] * 1000:.0f} mm during the lift"
        g = np.asarray(a["grasp"].T_world_grasp[:3, 3], float)
        dist = {k: _distance_to_box(g, m) for k, m in a["surfaces"].items()}
        k = min(dist, key=dist.get, default=None)
        if k is not None and dist[k] <= self.target_radius:
            return k, f"nothing rose; grasp centre {dist[k] * 1000:.0f} mm from object {k}'s bounding box"
        nearest = "" if k is None else f" (nearest: object {k}, {dist[k] * 1000:.0f} mm away)"
        return None, f"no real object at the grasp and none rose{nearest}"

    def _verdict(self, res: Any) -> Any:
        a = self._a
        target, why = self._target(a)
        moved = {k: float(np.linalg.norm(a["final"][k] - p)) for k, p in a["rest"].items()}
        out = replace(res, loop_outcome=res.outcome, target_id=target,
                      disturbed={k: d for k, d in moved.items() if k != target})
        out.neighbours_disturbed = any(d > self.pick.neighbour_tolerance for k, d in out.disturbed.items()
                                       if k not in self.handled)
        if res.outcome in _PASS_THROUGH:
            out.message = f"{res.message} [judge: {why}]"
        elif target is None:
            hit = {k: d for k, d in moved.items() if d > self.pick.neighbour_tolerance}
            out.outcome = Outcome.PHANTOM
            out.message = "attempt at an object that is not there: " + why + (
                "; it disturbed " + ", ".join(f"{k}: {d * 1000:.0f} mm" for k, d in hit.items()) if hit else "")
        else:
            out.trace = PickTrace(
                rest=a["rest"][target], lift=[r[target] for r in a["lift"]],
                translate=[r[target] for r in a["translate"]],
                lift_end=a.get("lift_end", {}).get(target), translate_end=a.get("translate_end", {}).get(target),
                final=a["final"][target], tcp_rest=a.get("tcp_rest"), tcp_lift_end=a.get("tcp_lift_end"),
                tcp_translate_end=a.get("tcp_translate_end"))
            out.judgement = judge_pick(out.trace, self.criteria)
            out.outcome, out.message = out.judgement.outcome, why
            before = a.get("before_close")
            if before is not None:
                hits = [k for k, p in a["rest"].items() if (k == target or k not in self.handled) and
                        np.linalg.norm(before[k] - p) > (self.pick.approach_tolerance if k == target
                                                         else self.pick.neighbour_tolerance)]
                if hits:
                    out.outcome = Outcome.COLLISION
                    out.message = "objects moved before the gripper closed: " + ", ".join(
                        f"{k}: {np.linalg.norm(before[k] - a['rest'][k]) * 1000:.1f} mm" for k in hits)
            if out.outcome is Outcome.NOT_RELEASED and out.judgement is not None:
                out.message = f"the object ended {out.judgement.final_height_change * 1000:.1f} mm above/below its " \
                              "rest height"
        if target is not None:
            self.handled.add(target)
        return out


def _distance_to_box(p_3: np.ndarray, mesh: Any) -> float:
    """Distance (m) from point ``p_3`` to the world-axis bounding box of ``mesh`` (0 inside it)."""
    v = np.asarray(mesh.verts_vx3, float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - p_3, p_3 - hi))))


class TrialJudge(PickJudge):
    """A trial's judge: per-pick verdicts plus the trial-level view (see the module docstring).

    The loop tells it what it perceived (:meth:`perceived`, one-way); it matches those reconstructions to the
    real objects at that moment, for the report only.
    """

    def __init__(self, backend: Any, criteria: SuccessCriteria | None = None, pick: PickConfig | None = None,
                 **kw: Any) -> None:
        super().__init__(backend, criteria, pick, **kw)
        self.names = {o.instance_id: o.name for o in backend.world.objects}
        self.real_ids = sorted(self.gt.object_poses())
        self.initial_meshes = self.gt.object_meshes()  # the true surfaces before anything moved (metrics)
        self.matches: dict[int, int] = {}  # reconstruction label -> real id
        self.matching: list[dict[str, Any]] = []
        #: every full capture the cameras made, ground truth included, in order (the loop got them without it)
        self.captures: list[Any] = []
        #: the paper's OCC of the first capture (0..1), measured when it was taken; None without masks or support
        self.occlusion: float | None = None
        self.occlusion_s: float = 0.0

    def saw(self, capture: Any) -> None:
        """Keep a full capture (masks, ideal depth, object ids) the loop received without its ground truth
        (:class:`torm.backend.blind.LoopBackend`'s ``truth_sink``), for scoring after the fact.

        The first capture's OCC is measured here, while the scene still stands as the cameras saw it: the solo
        silhouettes it renders must come from the same object poses as the capture's masks (after a pick they do
        not, and OCC read near zero)."""
        self.captures.append(capture)
        if len(self.captures) == 1 and capture.has_masks and hasattr(self.backend, "occlusion_ratio"):
            t0 = time.perf_counter()
            self.occlusion = float(self.backend.occlusion_ratio(capture))
            self.occlusion_s = time.perf_counter() - t0

    def perceived(self, point_clouds: list[ObjectPointCloud]) -> None:
        """Match the reconstructions (labels ``object_index``) to the real objects as they stand now."""
        from torm.metrics import match_clouds_to_meshes

        meshes = self.gt.object_meshes()
        ids = sorted(meshes)
        m = match_clouds_to_meshes([c.points_nx3 for c in point_clouds], [meshes[i] for i in ids])
        for p, g in m["pairs"]:
            self.matches[int(point_clouds[int(p)].object_index)] = ids[int(g)]
        pairs = [[int(point_clouds[int(p)].object_index), ids[int(g)]] for p, g in m["pairs"]]
        self.matching.append({k: v for k, v in m.items() if k != "pairs"} | {"pairs": pairs})

    def score(self, attempts: list[dict[str, Any]], not_reconstructed_reason: Any = None) -> dict[str, Any]:
        """Rows of the trial record from the loop's attempts (``{"label", "result": PickResult, ...}`` in order).

        Returns ``objects`` (one row per real object), ``attempts`` (one per attempt, judged), ``spurious_objects``
        (reconstructions matching no real object, with what their attempt did) and ``n_phantom_attempts``.
        """
        rows, by_target, unexecuted = [], {}, {}
        for a in attempts:
            res = a["result"]
            judged = self.verdicts.get(id(res)) if res is not None else None
            matched = self.matches.get(a["label"])
            row = {"label": a["label"], "matched_object": matched, "n_candidates": a.get("n_candidates", 0)}
            if judged is None:  # never moved: no candidate, unreachable
                outcome = res.outcome if res is not None else Outcome.NO_GRASP
                row |= {"outcome": outcome.value, "loop_outcome": outcome.value, "target_object": None,
                        "message": a.get("message") or (res.message if res is not None else "")}
                if matched is not None:
                    unexecuted.setdefault(matched, row)
            else:
                row |= {"outcome": judged.outcome.value, "loop_outcome": judged.loop_outcome.value,
                        "target_object": judged.target_id, "message": judged.message, "pick": judged.as_dict()}
                if judged.target_id is not None:
                    by_target.setdefault(judged.target_id, []).append(row)
            rows.append(row)
        objects = []
        for i in self.real_ids:
            name = self.names.get(i, f"object{i}")
            hits = by_target.get(i, [])
            best = next((r for r in hits if r["outcome"] == Outcome.SUCCESS.value), hits[-1] if hits else None)
            if best is None:
                best = unexecuted.get(i)
            if best is None:
                why = not_reconstructed_reason(i) if not_reconstructed_reason else "no reconstructed object matched it"
                objects.append({"object_id": i, "name": name, "outcome": Outcome.NOT_RECONSTRUCTED.value,
                                "message": why})
                continue
            entry = {"object_id": i, "name": name, "outcome": best["outcome"], "message": best["message"],
                     "attempts": len(hits)}
            if "pick" in best:
                entry["pick"] = best["pick"]
            objects.append(entry)
        spurious = [r for r in rows if r["matched_object"] is None]
        return {"objects": objects, "attempts": rows, "spurious_objects": spurious,
                "n_phantom_attempts": sum(r["outcome"] == Outcome.PHANTOM.value for r in rows),
                "matching": self.matching}
