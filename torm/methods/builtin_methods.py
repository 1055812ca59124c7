"""The built-in perception methods as :class:`~torm.methods.interface.PerceptionMethod` objects (issue 40).

``torm``, ``depth``, ``depth_fusion`` and ``oracle`` implement the same interface as a plug-in: ``name``,
``version``, ``needs`` and ``perceive(capture, context) -> list[ObjectEstimate]``. The trial loop builds them with
:func:`builtin_method` and calls :meth:`run`, which is ``perceive`` before it is reduced to the interface: the same
per-object clouds plus the method's diagnostics (timings, mask quality, reconstruction metrics) as a
:class:`torm.perception.Perception`. ``perceive`` is ``run`` with the diagnostics dropped, so a lab can call a
built-in exactly as it calls its own method (``load_method("depth")``, or
``torm.methods.builtin_methods:DepthMethod`` as a ``module:callable`` plug-in in a trial) and compose them.

Frames and units as in :mod:`torm.methods.interface`: world frame (robot base, z up), metres.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from torm.errors import ConfigError
from torm.methods.interface import MethodContext, Needs, ObjectEstimate
from torm.types import Capture, TriMesh

#: segmenters that read the RGB images (every other one reads the capture's masks)
IMAGE_SEGMENTERS = ("learned", "grounded_sam", "difference")


def _version() -> str:
    import torm

    return torm.__version__


def estimates_from(perception: Any) -> list[ObjectEstimate]:
    """A :class:`torm.perception.Perception` reduced to the interface's :class:`ObjectEstimate` list (points,
    normals, mesh; confidence 1)."""
    meshes = list(perception.meshes or []) + [None] * len(perception.point_clouds)
    return [ObjectEstimate(np.asarray(c.points_nx3), np.asarray(c.normals_nx3), meshes[k])
            for k, c in enumerate(perception.point_clouds)]


class _Builtin(ABC):
    """What the built-ins share: ``version`` (torm's) and ``perceive`` = :meth:`run` reduced to the interface."""

    name = ""
    needs = Needs()

    @property
    def version(self) -> str:
        return _version()

    @abstractmethod
    def run(self, capture: Capture, context: MethodContext) -> Any:
        """The method's :class:`torm.perception.Perception` (clouds, meshes and diagnostics) of ``capture``."""

    def perceive(self, capture: Capture, context: MethodContext) -> list[ObjectEstimate]:
        """Per-object estimates (world frame, m); see :meth:`run` for the diagnostics."""
        return estimates_from(self.run(capture, context))


class TormMethod(_Builtin):
    """TORM: silhouettes -> DMTet-Multi (or a visual hull) -> connectivity split -> surface samples.

    Args:
        segmenter: a segmenter name (``gt``, ``noisy``, ``learned``, ``grounded_sam``, ``difference``) or a built
            segmenter object (anything with ``segment(capture)``).
        segmenter_options: that segmenter's config fields (ignored for a segmenter object).
        reconstruction: a :class:`torm.reconstruction.ReconstructionConfig` or a mapping of its fields (None:
            defaults).
        segmenter_name: the name of a segmenter object (decides ``needs``: an image segmenter reads RGB).

    ``needs``: RGB for an image segmenter, the capture's masks otherwise (simulator masks in simulation, a
    recorded capture's masks otherwise), the reference pass for ``difference`` or a reference-mode model.
    """

    name = "torm"

    def __init__(self, segmenter: Any = "gt", segmenter_options: Mapping[str, Any] | None = None,
                 reconstruction: Any = None, segmenter_name: str | None = None) -> None:
        from torm.config import from_dict
        from torm.reconstruction import ReconstructionConfig

        if isinstance(segmenter, str):
            from torm.segmentation import make_segmenter

            self.segmenter_name = segmenter
            self.segmenter = make_segmenter(segmenter, dict(segmenter_options or {}) or None)
        else:
            if not hasattr(segmenter, "segment"):
                raise ConfigError(f"TormMethod: segmenter must be a name or have segment(capture), got "
                                  f"{type(segmenter).__name__}")
            self.segmenter_name = segmenter_name or str(getattr(segmenter, "name", type(segmenter).__name__))
            self.segmenter = segmenter
        if reconstruction is None or isinstance(reconstruction, Mapping):
            reconstruction = from_dict(ReconstructionConfig, dict(reconstruction or {}), where="reconstruction")
        self.reconstruction = reconstruction
        reads_images = self.segmenter_name in IMAGE_SEGMENTERS
        self.needs = Needs(rgb=reads_images, masks=not reads_images,
                           reference=bool(getattr(self.segmenter, "needs_reference", False)))

    def run(self, capture: Capture, context: MethodContext) -> Any:
        """:func:`torm.perception.perceive_torm` on ``capture`` (its ``table_height`` set to the context's)."""
        from dataclasses import replace

        from torm.perception import perceive_torm

        if capture.table_height != context.table_height:
            capture = replace(capture, table_height=context.table_height)
        return perceive_torm(capture, self.segmenter, self.reconstruction)


class DepthMethod(_Builtin):
    """Single-view sensor depth inside the capture's masks, the unseen back mirrored
    (:func:`torm.perception.depth_point_clouds`).

    Args:
        view: the capture view to read (None: its most top-down one; a captured subset has that one only).
        symmetric_completion: add the mirrored back (an antipodal planner needs both sides).
        min_pixels: fewest valid depth pixels an object needs.
    """

    name = "depth"

    def __init__(self, view: int | None = None, symmetric_completion: bool = True, min_pixels: int = 30) -> None:
        if view is not None and int(view) < 0:
            raise ConfigError(f"DepthMethod: view must be >= 0 or None (the most top-down view), got {view}")
        if int(min_pixels) < 3:
            raise ConfigError(f"DepthMethod: min_pixels must be >= 3, got {min_pixels}")
        self.view = None if view is None else int(view)
        self.symmetric_completion = bool(symmetric_completion)
        self.min_pixels = int(min_pixels)
        self.needs = Needs(rgb=False, sensor_depth=True, masks=True, views="top_down")

    def run(self, capture: Capture, context: MethodContext) -> Any:
        from torm.perception import Perception, depth_point_clouds, most_top_down_view

        if len(capture.views) == 1:
            view = 0
        elif self.view is not None:
            if self.view >= len(capture.views):
                raise ConfigError(f"DepthMethod: view {self.view} is outside the capture's views "
                                  f"0..{len(capture.views) - 1}")
            view = self.view
        else:
            view = most_top_down_view(capture)
        clouds = depth_point_clouds(capture, view, context.n_points, context.rng, self.min_pixels,
                                    self.symmetric_completion)
        return Perception(clouds, [None] * len(clouds), {"baseline": "single-view depth, symmetric completion"})


class DepthFusionMethod(_Builtin):
    """Every view's sensor depth fused into a TSDF (Open3D), per-object meshes cut by the capture's masks
    (:func:`torm.perception.perceive_depth_fusion`).

    Args:
        fusion: a :class:`torm.fusion.FusionConfig` or a mapping of its fields (None: defaults).
    """

    name = "depth_fusion"

    def __init__(self, fusion: Any = None) -> None:
        from torm.config import from_dict
        from torm.fusion import FusionConfig

        if fusion is None or isinstance(fusion, Mapping):
            fusion = from_dict(FusionConfig, dict(fusion or {}), where="fusion")
        self.fusion = fusion
        self.needs = Needs(rgb=False, sensor_depth=True, masks=True, views="all")

    def run(self, capture: Capture, context: MethodContext) -> Any:
        from torm.perception import perceive_depth_fusion

        return perceive_depth_fusion(capture, self.fusion, context.n_points, context.rng)


class OracleMethod(_Builtin):
    """Samples of the true object meshes: the upper bound, simulation only.

    Args:
        meshes: a callable returning ``{instance id: TriMesh}`` (world frame, m): the simulator's true meshes,
            which the harness grants this method alone. The real backend has none.
    """

    name = "oracle"

    def __init__(self, meshes: Callable[[], dict[int, TriMesh]] | None = None) -> None:
        if meshes is None:
            raise ConfigError("method 'oracle' needs the simulator's true meshes (a simulated backend); the real "
                              "backend has none: use method=torm")
        self.meshes = meshes
        self.needs = Needs(rgb=False, masks=True)

    def run(self, capture: Capture, context: MethodContext) -> Any:
        from torm.perception import Perception, oracle_point_clouds

        clouds, meshes = oracle_point_clouds(self.meshes(), context.n_points, context.rng)
        return Perception(clouds, meshes, {})


#: name -> class of every built-in method
BUILTIN_CLASSES: dict[str, type[_Builtin]] = {"torm": TormMethod, "depth": DepthMethod,
                                               "depth_fusion": DepthFusionMethod, "oracle": OracleMethod}


def segmenter_for(config: Any) -> Any:
    """The segmenter a :class:`torm.pipeline.TrialConfig`'s ``segmentation`` names, built (``noisy`` draws its
    errors from the trial's seed and ``segmentation.preset``)."""
    from torm.segmentation import make_segmenter

    s = config.segmentation
    opts = dict(s.options)
    if s.segmenter == "noisy":
        opts.setdefault("preset", s.preset)
        opts.setdefault("seed", config.seed)
    seg = make_segmenter(s.segmenter, opts or None)
    if s.segmenter == "learned" and "classes" not in opts:
        prompt_scenario_targets(seg, config.scenario)
    return seg


def prompt_scenario_targets(seg: Any, scenario: str) -> tuple[str, ...]:
    """Give a learned segmenter the scenario's ``targets`` as its prompt of classes (the paper's text prompt names the
    opaque cup in RW2 and RW5). A model without the class head answers ``transparent`` only: it keeps its prompt and a
    warning names the classes it cannot pick and the model that can. Returns the prompt in use. A scenario name that
    is not in the library (a recorded capture) leaves the prompt as it is."""
    import dataclasses
    import logging

    from torm.errors import UnknownNameError

    try:
        from sim.scenes.scenario import get_scenario

        targets = tuple(get_scenario(scenario).targets)
    except (ImportError, UnknownNameError):
        return tuple(seg.config.classes)
    can = tuple(t for t in targets if t in seg.classes_available)
    if len(can) < len(targets):
        logging.getLogger(__name__).warning(
            "scenario %s targets %s, but %s has no class head and cannot be prompted for %s objects (it marks what "
            "it was trained on; learned.model=v7 picks both classes)", scenario, ", ".join(targets),
            seg.config.model_path.name, ", ".join(t for t in targets if t not in can))
    if can and can != tuple(seg.config.classes):
        seg.config = dataclasses.replace(seg.config, classes=can)
    return tuple(seg.config.classes)


def builtin_method(config: Any, oracle_meshes: Callable[[], dict[int, TriMesh]] | None = None) -> _Builtin:
    """The built-in method of a :class:`torm.pipeline.TrialConfig` (``config.method`` must be a built-in), built
    from the trial's settings: its segmenter, reconstruction, fusion, ``depth_view``; ``oracle_meshes`` for
    ``oracle``."""
    if config.method == "torm":
        return TormMethod(segmenter_for(config), reconstruction=config.reconstruction,
                          segmenter_name=config.segmentation.segmenter)
    if config.method == "depth":
        return DepthMethod(view=config.depth_view)
    if config.method == "depth_fusion":
        return DepthFusionMethod(config.fusion)
    if config.method == "oracle":
        return OracleMethod(oracle_meshes)
    from torm.errors import UnknownNameError

    raise UnknownNameError("built-in method", config.method, tuple(BUILTIN_CLASSES))


__all__ = ["BUILTIN_CLASSES", "DepthFusionMethod", "DepthMethod", "OracleMethod", "TormMethod", "builtin_method",
           "estimates_from", "segmenter_for"]
