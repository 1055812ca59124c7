"""A fast, deterministic stand-in trial function for the benchmark-runner tests.

``run(spec, overrides, record_path)`` returns a record shaped like :func:`torm.pipeline.run_trial`'s,
drawn from ``numpy.random.default_rng(spec.seed)`` (so the same seed gives the same record). Its
behaviour is steered by ``--set fake.<what>=...`` overrides (a list of ``scenario/trial`` or full keys):

- ``fake.sleep_s``: seconds every trial sleeps first;
- ``fake.hang``: sleep for an hour; ``fake.crash``: ``os._exit(3)``; ``fake.segv``: SIGSEGV itself;
- ``fake.crash_once``: a marker file path; crash (``os._exit(3)``) when it does not exist yet, creating it;
- ``fake.raise``: raise RuntimeError; ``fake.physics``: raise an exception class named PhysicsError;
- ``fake.blowup``: return a record whose failure is ``physics_error`` (what run_trial does).

With a ``record_path`` it writes a small file there (stands in for a rerun recording).
"""

from __future__ import annotations

import os
import signal
import time
from typing import Any

import numpy as np

from torm.config import parse_override

FAILURES = ("slipped_during_lift", "no_grasp_found", "collision_on_approach")
SUCCESS_P = {"torm": 0.75, "depth": 0.35, "oracle": 0.9}


class PhysicsError(RuntimeError):
    """Same class name as torm.execution.errors.PhysicsError (the runner matches on the name)."""


def _options(overrides: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for text in overrides:
        path, value = parse_override(text)
        if path[0] == "fake":
            out[path[1]] = value
    return out


def _hit(spec: Any, keys: Any) -> bool:
    if not keys:
        return False
    keys = [keys] if isinstance(keys, str) else list(keys)
    return f"{spec.scenario}/{spec.trial}" in keys or spec.key in keys


def run(spec: Any, overrides: tuple[str, ...] = (), record_path: str | None = None) -> dict[str, Any]:
    opts = _options(overrides)
    if opts.get("sleep_s"):
        time.sleep(float(opts["sleep_s"]))
    if _hit(spec, opts.get("hang")):
        time.sleep(3600)
    if _hit(spec, opts.get("crash")):
        os._exit(3)
    if opts.get("crash_once") and not os.path.exists(opts["crash_once"]):
        open(opts["crash_once"], "w").close()
        os._exit(3)
    if _hit(spec, opts.get("segv")):
        os.kill(os.getpid(), signal.SIGSEGV)
    if _hit(spec, opts.get("sigint")):
        os.kill(os.getpid(), signal.SIGINT)  # someone stops the worker with Ctrl-C's signal
        time.sleep(5)
    if _hit(spec, opts.get("raise")):
        raise RuntimeError(f"fake failure in {spec.key}")
    if _hit(spec, opts.get("physics")):
        raise PhysicsError("fake NaN in qacc")
    rng = np.random.default_rng(spec.seed)
    p = SUCCESS_P[spec.method]
    objects = []
    for k, name in enumerate(spec.objects, start=1):
        ok = rng.random() < p
        outcome = "success" if ok else FAILURES[int(rng.integers(len(FAILURES)))]
        objects.append({"object_id": k, "name": name, "outcome": outcome, "message": "",
                        "pick": {"attempts": int(rng.integers(1, 4)), "lift_m": float(rng.uniform(0.2, 0.26))}})
    failure = None
    if _hit(spec, opts.get("blowup")):
        objects[-1]["outcome"] = "physics_error"
        failure = "physics_error"
    n = len(spec.objects)
    perception: dict[str, Any] = {"n_objects_present": n,
                                  "n_objects_found": int(n - (rng.random() < 0.2 and n > 1)),
                                  "chamfer_mm_mean": float(rng.uniform(1.0, 6.0)), "reconstruction_s": 1.0}
    if spec.method == "torm":
        perception["silhouette_iou_mean"] = float(rng.uniform(0.8, 0.98))
        perception["occlusion_ratio"] = round(0.1 * len(spec.objects), 3)
    timings = {"setup": 0.1, "capture": 0.2, "segmentation": 0.3 if spec.method == "torm" else 0.0,
               "reconstruction": 1.0, "grasp_planning": 0.4, "execution": 2.0}
    timings["total"] = sum(timings.values())
    if record_path:
        with open(record_path, "w") as f:
            f.write(f"fake recording of {spec.key}\n")
    n_success = sum(o["outcome"] == "success" for o in objects)
    extra = np.random.default_rng(spec.seed + 1)  # phantoms from their own stream: the draws above stay as they were
    spurious = [{"label": 1000 + n + j, "matched_object": None, "outcome": "phantom_attempt"}
                for j in range(int(spec.method == "torm" and extra.random() < 0.3))]
    context = {"method": spec.method, "realism": str(opts.get("realism", "measured")), "renderer": "mujoco",
               "segmenter": "gt" if spec.method == "torm" else None, "depth_model": "ideal", "table": "declared",
               "backend": "sim"}
    return {"scenario": spec.scenario, "seed": spec.seed, "method": spec.method, "config": {"fake": opts},
            "context": context,
            "spurious_objects": spurious, "n_phantom_attempts": len(spurious),
            "versions": {"fake": "1"}, "timings": timings, "perception": perception, "objects": objects,
            "failure": failure, "n_objects": n, "n_success": n_success, "success_rate": n_success / n if n else 0.0}


def safe_stop(spec: Any, overrides: tuple[str, ...] = ()) -> Any:
    """The default module's driver-side stop (:func:`torm.bench.trial.safe_stop`) without the ``fake.`` keys."""
    from torm.bench.trial import safe_stop as real_safe_stop

    return real_safe_stop(spec, tuple(o for o in overrides if not o.startswith("fake.")))


def real_arm(spec: Any, overrides: tuple[str, ...] = (), record_path: str | None = None) -> dict[str, Any]:
    """A trial on the real backend (``--backend real``) that moves the arm slowly for ``fake.move_s`` seconds.

    Builds the backend exactly as a trial does (``make_real_backend`` from the resolved trial config) and
    closes it in ``finally`` like ``run_trial``: the stop path a SIGTERMed worker must run.
    """
    from torm.bench.trial import trial_config
    from torm.execution.trajectory import min_jerk_segment
    from torm.hardware import make_real_backend

    opts = _options(overrides)
    config = trial_config(spec, tuple(o for o in overrides if not o.startswith("fake.")))
    backend = make_real_backend(config)
    try:
        q0 = backend.arm.state().q
        times, q = min_jerk_segment(q0, q0 + np.array([0.3, -0.1, 0.1, 0.0, 0.1, 0.0]),
                                    float(opts.get("move_s", 30.0)), 0.05)
        backend.arm.follow_trajectory(times, q)
    finally:
        backend.close()
    return {"objects": [{"object_id": 1, "name": spec.objects[0], "outcome": "success", "message": ""}]}
