"""The default trial function of ``torm bench``: one closed-loop trial of :mod:`torm.pipeline`.

Trial-function contract (what ``BenchConfig.trial_fn`` points at)::

    fn(spec: TrialSpec, overrides: tuple[str, ...], record_path: str | None) -> dict

It runs in a fresh worker process (:mod:`torm.bench.worker`) and returns a JSON-ready record with at
least ``objects: [{object_id, name, outcome, ...}]`` (``outcome`` = ``"success"`` for a success);
``n_objects``/``n_success``/``success_rate`` are filled in when missing. It should be deterministic
given ``spec.seed``. Raising is fine: the runner records the exception's category.

Recording hook: when ``record_path`` is given (``torm bench --record failures|all``) the function may
write a rerun ``.rrd`` recording there; the runner keeps it for failed trials (``failures``) or all
trials (``all``). This one records every capture the robot took (camera frusta, the images of a few
views, instance masks), the true object meshes at the start, and the trial's outcome as text. A
recording problem is logged and never fails the trial.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from typing import Any

from torm.bench.spec import TrialSpec

log = logging.getLogger(__name__)

RECORD_IMAGE_VIEWS = 4  # image data is logged for this many views per capture; frusta for all
#: What benchmark trials default to, under the run's overrides: the measured realism profile (a single
#: ``torm trial`` defaults to ``ideal``). ``--set world.realism=ideal`` runs a benchmark in the ideal world.
BENCH_DEFAULTS: dict[str, Any] = {"world": {"realism": "measured"}}


def trial_config(spec: TrialSpec, overrides: tuple[str, ...] = ()) -> Any:
    """The :class:`torm.pipeline.TrialConfig` of ``spec``: :data:`BENCH_DEFAULTS` + ``overrides`` + the grid cell."""
    from torm.config import from_dict
    from torm.pipeline import TrialConfig

    base = from_dict(TrialConfig, BENCH_DEFAULTS, overrides)
    return dataclasses.replace(base, scenario=spec.scenario, seed=spec.seed, method=spec.method)


def check_overrides(overrides: tuple[str, ...]) -> dict[str, Any]:
    """The resolved base TrialConfig (defaults + overrides) as plain data, for the run's manifest.

    Raises ConfigError now, in the runner, when the overrides do not make a valid TrialConfig
    (instead of every trial failing with ``config_error``). ``scenario``/``seed``/``method`` are set per trial.
    """
    from torm.config import from_dict, to_dict
    from torm.pipeline import TrialConfig

    return to_dict(from_dict(TrialConfig, BENCH_DEFAULTS, overrides))


def run_spec(spec: TrialSpec, overrides: tuple[str, ...] = (), record_path: str | None = None) -> dict[str, Any]:
    """Run the closed-loop trial of ``spec`` and return :func:`torm.pipeline.run_trial`'s record."""
    from torm.pipeline import run_trial

    config = trial_config(spec, overrides)
    if record_path is None:
        return run_trial(config)
    from torm.pipeline import make_backend

    t0 = time.perf_counter()
    backend = make_backend(config)
    setup_s = time.perf_counter() - t0  # run_trial only times the setup of a backend it builds itself
    recorder = _Recorder(record_path, spec)
    try:
        recorder.start(backend)
        record = run_trial(config, backend=_RecordingBackend(backend, recorder))
        timings = record.setdefault("timings", {})
        timings["setup"] = timings.get("setup", 0.0) + setup_s
        if "total" in timings:
            timings["total"] += setup_s
        recorder.finish(record)
        return record
    finally:
        backend.close()


class _Recorder:
    """Writes a rerun recording; every method swallows (and logs) its own errors."""

    def __init__(self, path: str, spec: TrialSpec) -> None:
        self.path, self.spec, self.rec, self.n_captures = path, spec, None, 0
        try:
            import rerun as rr

            self.rec = rr.RecordingStream("torm-bench", recording_id=spec.key)
            self.rec.save(path)
        except Exception as exc:  # noqa: BLE001 - recording is best effort
            log.warning("recording %s disabled: %s", path, exc)
            self.rec = None

    def start(self, backend: Any) -> None:
        if self.rec is None:
            return
        try:
            import rerun as rr

            from torm.viz import log_mesh

            self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            gt = getattr(backend, "ground_truth", None)
            if gt is not None and hasattr(gt, "object_meshes"):
                for k, mesh in gt.object_meshes().items():
                    log_mesh(self.rec, f"world/truth/object_{k}", mesh)
        except Exception as exc:  # noqa: BLE001
            log.warning("recording: could not log the scene: %s", exc)

    def capture(self, capture: Any) -> None:
        if self.rec is None:
            return
        try:
            from torm.viz import log_capture

            n = len(capture)
            views = range(0, n, max(1, n // RECORD_IMAGE_VIEWS))
            log_capture(self.rec, capture, root=f"world/capture_{self.n_captures}", image_views=list(views))
            self.n_captures += 1
        except Exception as exc:  # noqa: BLE001
            log.warning("recording: could not log a capture: %s", exc)

    def finish(self, record: dict[str, Any]) -> None:
        if self.rec is None:
            return
        try:
            import rerun as rr

            summary = {k: record.get(k) for k in ("scenario", "seed", "method", "failure", "n_objects", "n_success")}
            summary["objects"] = [{k: o.get(k) for k in ("object_id", "name", "outcome", "message")}
                                  for o in record.get("objects", [])]
            self.rec.log("trial/result", rr.TextDocument(json.dumps(summary, indent=2)), static=True)
            self.rec.flush()
        except Exception as exc:  # noqa: BLE001
            log.warning("recording: could not finish %s: %s", self.path, exc)


class _RecordingBackend:
    """Delegates everything to the wrapped backend; also logs each capture to the recording."""

    def __init__(self, inner: Any, recorder: _Recorder) -> None:
        self._inner, self._recorder = inner, recorder

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def capture(self, *args: Any, **kwargs: Any) -> Any:
        cap = self._inner.capture(*args, **kwargs)
        self._recorder.capture(cap)
        return cap


__all__ = ["BENCH_DEFAULTS", "check_overrides", "run_spec", "trial_config"]
