"""What defines a closed-loop trial: :class:`TrialConfig` and its sections (capture, world, segmentation).

Distances in m, times in s. The loop (:mod:`torm.loop`) and the trial runner (:mod:`torm.pipeline`) both read
these; they live below both so that neither imports the other for them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from torm import vocabulary as _vocab
from torm.capture.render_settings import PbrSettings
from torm.config import check_finite
from torm.errors import ConfigError, UnknownNameError
from torm.execution.pick import PickConfig
from torm.execution.success import SuccessCriteria
from torm.fusion import FusionConfig
from torm.grasp.planner import GraspPlannerConfig
from torm.perception import METHODS
from torm.reconstruction.api import ReconstructionConfig

#: Sources of the table height the loop plans with (``TrialConfig.table``): ``declared`` (the cell's declared
#: calibration) or ``capture`` (a plane fitted to the capture's sensor depth).
TABLE_SOURCES = ("declared", "capture")

#: Image renderers of the simulated capture (``capture.renderer``).
RENDERERS = _vocab.RENDERERS
#: Sensor-depth models of the simulated depth camera (``capture.depth_model``, :mod:`sim.depth`): ``ideal`` is
#: exact z-depth of every opaque surface with glass invisible (the camera sees straight through it);
#: ``statistical`` a D455 whose glass pixels go missing / see through / read near the surface with
#: incidence-dependent probabilities; ``stereo`` an active-stereo D455 simulation (IR dots + SGBM).
DEPTH_MODELS = _vocab.DEPTH_MODELS
#: Realism profiles of the simulated world (``world.realism``): ``ideal`` = nominal physics, exact
#: cameras, exact tracking; ``measured`` = contact, grip force, object mass, calibration and execution errors
#: drawn per trial from sourced ranges (``sim/realism.py``, table in ``sim/REALISM.md``).
REALISM_PROFILES = _vocab.REALISM_PROFILES
#: Factor groups of a realism profile (``world.factors``; empty = all of them).
REALISM_FACTORS = _vocab.REALISM_FACTORS


@dataclass(frozen=True)
class CaptureSettings:
    """Multi-view capture: number of views and image scale of the 1280x720, 91.5 deg HFOV camera.

    Attributes:
        n_views: number of views.
        scale: image scale (0.5 -> 640x360).
        renderer: who renders the RGB images (one of :data:`RENDERERS`): ``mujoco`` rasterises (glass as alpha
            blending), ``pbr`` path-traces with Mitsuba 3 (refracting glass; ``sim.render``). Cameras, depth and
            instance masks are the same for both.
        pbr: settings of the ``pbr`` renderer (samples, bounces, denoiser, variant, cache).
        depth_model: how the sensor depth is simulated (one of :data:`DEPTH_MODELS`).
        depth_options: overrides of the depth model's config fields (e.g. ``{"correlation_px": 0}`` for
            ``statistical``; see ``sim/depth/README.md``); unknown keys are rejected when the backend is built.
        reference: also capture each view over the empty workspace (a reference pass, ``CameraView.reference_rgb``)
            for reference-mode segmenters; in simulation the objects are hidden for that pass.
        reference_dir: instead, a recorded reference pass: a capture folder of the empty workspace through the same
            camera path (``torm capture --empty`` in simulation, ``torm capture --backend real --empty`` over
            the table cleared by hand). Each trial's views
            are paired with it by camera pose (refused beyond 2 mm / 0.5 deg, or from another camera, renderer or
            image size) and it is refused before segmentation when the static background no longer matches (the
            table, the camera or the light changed; ``torm.segmentation.reference``).
    """

    n_views: int = 50
    scale: float = 0.5
    renderer: str = "mujoco"
    depth_model: str = "ideal"
    depth_options: dict[str, Any] = field(default_factory=dict)
    pbr: PbrSettings = field(default_factory=PbrSettings)
    reference: bool = False
    reference_dir: str = ""

    def __post_init__(self) -> None:
        if self.n_views < 1 or not self.scale > 0:
            raise ConfigError("capture.n_views must be >= 1 and capture.scale > 0")
        if self.reference and self.reference_dir:
            raise ConfigError("capture.reference renders a reference pass and capture.reference_dir reads a recorded "
                              "one: set one of them")
        if self.renderer not in RENDERERS:
            raise UnknownNameError("capture.renderer", self.renderer, RENDERERS)
        if self.depth_model not in DEPTH_MODELS:
            raise UnknownNameError("capture.depth_model", self.depth_model, DEPTH_MODELS)


@dataclass(frozen=True)
class WorldSettings:
    """The simulated world's fidelity.

    Attributes:
        realism: realism profile (one of :data:`REALISM_PROFILES`); ``ideal`` is the default of a single trial,
            ``measured`` the default of benchmark runs (``torm bench``).
        factors: with ``measured``, draw only these factor groups (:data:`REALISM_FACTORS`), the others stay
            ideal; empty = all. The grip force group replaces ``pick.grip_force`` by the drawn pad force.
        stress: with ``stress`` (margin sweeps, not realism): how many times beyond the worst end of each sourced
            range the factors are pushed (>= 1; ``sim.realism.MeasuredRanges.stressed``).
    """

    realism: str = "ideal"
    factors: tuple[str, ...] = ()
    stress: float = 1.0

    def __post_init__(self) -> None:
        if self.realism not in REALISM_PROFILES:
            raise UnknownNameError("world.realism", self.realism, REALISM_PROFILES)
        object.__setattr__(self, "factors", tuple(self.factors))
        for f in self.factors:
            if f not in REALISM_FACTORS:
                raise UnknownNameError("world.factors entry", f, REALISM_FACTORS)
        if len(set(self.factors)) != len(self.factors):
            raise ConfigError(f"world.factors {list(self.factors)} lists a factor twice")
        if not (np.isfinite(self.stress) and self.stress >= 1):
            raise ConfigError(f"world.stress must be >= 1 (1 = the worst end of each sourced range), got {self.stress}")
        if self.stress != 1.0 and self.realism != "stress":
            raise ConfigError(f"world.stress={self.stress} only applies with world.realism=stress")


@dataclass(frozen=True)
class SegmentationSettings:
    """Silhouette source: ``gt`` (simulator masks), ``noisy`` (error model preset), ``grounded_sam``,
    ``learned`` (the shipped U-Net; reads the rendered RGB) or ``difference`` (scene minus the reference pass; needs
    ``capture.reference``). A reference-mode ``learned`` model (``options.model``) also needs ``capture.reference``.

    ``options`` is passed to the segmenter's own config (e.g. ONNX paths for ``grounded_sam``, thresholds or
    another model file for ``learned``).
    """

    segmenter: str = "gt"
    preset: str = "paper"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        valid = ("gt", "noisy", "grounded_sam", "learned", "difference")
        if self.segmenter not in valid:
            raise UnknownNameError("segmenter", self.segmenter, valid)


@dataclass(frozen=True)
class TrialConfig:
    """Everything that defines a trial. Distances in m, times in s.

    Attributes:
        scenario: scenario name (``torm scenes list``).
        seed: scene layout seed; also seeds segmentation noise and sampling.
        method: ``torm`` | ``depth`` (single-view depth) | ``depth_fusion`` (TSDF fusion of every view's depth) |
            ``oracle`` (see :mod:`torm.perception`), or a plug-in: an installed ``torm.methods`` entry point's name
            or ``package.module:callable`` (:mod:`torm.methods`; ``torm methods list``).
        method_options: keyword arguments for a plug-in method's factory (recorded, hashed in the context).
        planner: the grasp planner: ``antipodal`` (default), ``onnx_graspnet``, a ``torm.planners`` entry point or
            ``package.module:callable`` (:mod:`torm.methods.planner_plugins`).
        planner_options: keyword arguments for the planner's factory.
        backend: ``sim`` or ``real``.
        robot: robot folder name or robot YAML path.
        re_perceive: capture and reconstruct again before every pick after the first.
        depth_view: layout view index for the single-view depth baseline (None: the most top-down view).
        fusion: TSDF settings of the ``depth_fusion`` baseline.
        place_area: ((x_min, y_min), (x_max, y_max)) of the table (m, world) where the 20 cm translation may
            end: the released object must land inside it, away from the other objects.
        hardware_config: hardware YAML for ``backend="real"`` (host, serial port, hand-eye file...;
            default: $TORM_HARDWARE_CONFIG).
        arm_robot: allow the real arm to move (otherwise the real backend refuses every motion).
        table: where the loop's table height comes from (:data:`torm.loop.TABLE_SOURCES`): ``declared`` (the
            cell's declared calibration: the hardware config, or the scenario's declaration in simulation) or
            ``capture`` (a plane fitted to the capture's depth).
    """

    scenario: str = "rw3"
    seed: int = 0
    method: str = "torm"
    method_options: dict[str, Any] = field(default_factory=dict)
    planner: str = "antipodal"
    planner_options: dict[str, Any] = field(default_factory=dict)
    backend: Literal["sim", "real"] = "sim"
    robot: str = "inovo_2f85"
    re_perceive: bool = False
    depth_view: int | None = None
    place_area: tuple[tuple[float, float], tuple[float, float]] = ((0.25, -0.35), (0.85, 0.35))
    hardware_config: str | None = None
    arm_robot: bool = False
    table: str = "declared"
    world: WorldSettings = field(default_factory=WorldSettings)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    segmentation: SegmentationSettings = field(default_factory=SegmentationSettings)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    grasp: GraspPlannerConfig = field(default_factory=GraspPlannerConfig)
    pick: PickConfig = field(default_factory=PickConfig)
    success: SuccessCriteria = field(default_factory=SuccessCriteria)

    def __post_init__(self) -> None:
        check_finite(self, "TrialConfig")  # NaN / inf in any float field of any section (torm.config)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be a non-negative integer (0, 1, 2, ...), got {self.seed!r}")
        if self.method not in METHODS:  # a plug-in (entry point or module:callable), or an unknown name
            from torm.methods import check_method_name

            check_method_name(self.method)
        if self.planner != "antipodal":
            from torm.methods.planner_plugins import check_planner_name

            check_planner_name(self.planner)
        if self.table not in TABLE_SOURCES:
            raise UnknownNameError("table", self.table, TABLE_SOURCES)
        if self.backend not in ("sim", "real"):
            raise UnknownNameError("backend", self.backend, ("sim", "real"))
        lo, hi = np.asarray(self.place_area, dtype=float)
        if lo.shape != (2,) or not np.all(hi > lo):
            raise ConfigError(f"place_area must be ((x_min, y_min), (x_max, y_max)) with max > min, got "
                              f"{self.place_area}")
        self._check_success_is_reachable()
        if self.backend == "sim":  # a misspelt scenario is refused here, not after the backend started
            from sim.scenes.scenario import get_scenario

            get_scenario(self.scenario)
        if self.segmentation.segmenter == "difference" and not (self.capture.reference or self.capture.reference_dir):
            raise ConfigError("segmentation.segmenter=difference reads each view's reference pass: also set "
                              "capture.reference=true (rendered, simulation) or capture.reference_dir=DIR (recorded)")


    def _check_success_is_reachable(self) -> None:
        """The success test asks for no more than the pick does: a success criterion beyond the commanded motion
        fails every trial (a 1e9 m translation judged as arm tracking errors); ConfigError naming both keys."""
        pick, ok = self.pick, self.success
        commanded_lift = pick.lift_height + pick.lift_margin
        if ok.translation > pick.translate_distance + ok.height_tolerance:
            raise ConfigError(f"success.translation={ok.translation:g} m is more than the pick moves the object "
                              f"sideways (pick.translate_distance={pick.translate_distance:g} m): no trial could "
                              "succeed; lower success.translation or raise pick.translate_distance with it")
        if ok.lift_height > commanded_lift + ok.height_tolerance:
            raise ConfigError(f"success.lift_height={ok.lift_height:g} m is more than the pick lifts "
                              f"(pick.lift_height + pick.lift_margin = {commanded_lift:g} m): no trial could "
                              "succeed; lower success.lift_height or raise pick.lift_height with it")


__all__ = ["DEPTH_MODELS", "REALISM_FACTORS", "REALISM_PROFILES", "RENDERERS", "TABLE_SOURCES",
           "CaptureSettings", "SegmentationSettings", "TrialConfig", "WorldSettings"]
