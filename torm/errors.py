"""Exception hierarchy. Every error raised by torm derives from :class:`TormError`.

A message says what was wrong and how to fix it. Only the benchmark runner turns errors into
recorded failure categories; library code raises.
"""

from __future__ import annotations

from collections.abc import Iterable


class TormError(Exception):
    """Root of every torm error."""


class ConfigError(TormError):
    """A config file, override or dataclass field is invalid."""


class UnknownNameError(TormError, KeyError):
    """A name (scenario, object, method, preset...) is not one of the valid choices."""

    def __init__(self, kind: str, name: str, valid: Iterable[str]) -> None:
        self.kind = kind
        self.name = name
        self.valid = sorted(valid)
        super().__init__(f"unknown {kind} {name!r}; valid choices: {', '.join(self.valid)}")

    def __str__(self) -> str:  # KeyError would otherwise repr() the message
        return self.args[0]


class SceneError(TormError):
    """A robot, object or scenario description cannot be built or simulated."""


class CaptureError(TormError):
    """A capture (views, poses, masks, depth) is malformed or inconsistent."""


class SegmentationError(TormError):
    """Silhouette extraction failed or its inputs are invalid."""


class ModelFileError(SegmentationError):
    """A model file (ONNX weights, vocabulary) is missing or does not match what is expected."""


class ReconstructionError(TormError):
    """Reconstruction inputs are inconsistent or the reconstruction is unusable."""


class GraspError(TormError):
    """Grasp planning inputs are invalid."""


class ExecutionError(TormError):
    """Motion execution failed (IK divergence, unreachable target, physics blow-up)."""


class HardwareError(TormError):
    """A real-hardware device cannot be reached or refused a command."""


class BenchmarkError(TormError):
    """A benchmark run folder, suite or results file is invalid."""


class OutputError(TormError):
    """An output file or folder (``--out``, ``--record``) cannot be written."""


class PluginError(TormError):
    """A plug-in method that cannot be found or loaded, or whose output breaks the interface (names the plug-in)."""
