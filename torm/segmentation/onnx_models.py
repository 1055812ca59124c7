"""Loading ONNX sessions and checking their input/output signatures against what torm feeds them.

A signature lists, per role, the accepted names (exports differ: ``img`` vs ``samples``), the rank and,
optionally, static dimensions. :func:`open_session` raises :class:`~torm.errors.ModelFileError` naming
the file and the expected signature when the file is missing, unreadable or does not match.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ModelFileError

log = logging.getLogger(__name__)

_ORT_DTYPES = {
    "tensor(float)": np.float32, "tensor(double)": np.float64, "tensor(float16)": np.float16,
    "tensor(int64)": np.int64, "tensor(int32)": np.int32, "tensor(bool)": np.bool_, "tensor(uint8)": np.uint8,
}


@dataclass(frozen=True)
class TensorSpec:
    """One expected tensor: a role, accepted names, rank and static dims (None = any)."""

    role: str
    names: tuple[str, ...]
    dims: tuple[int | None, ...]
    required: bool = True

    def describe(self) -> str:
        shape = ", ".join("?" if d is None else str(d) for d in self.dims)
        return f"{'|'.join(self.names)} ({shape})"


@dataclass
class BoundSession:
    """An onnxruntime session plus the actual names bound to each role and the input dtypes."""

    path: Path
    session: Any
    inputs: dict[str, str]
    outputs: dict[str, str]
    input_dtypes: dict[str, Any]

    def run(self, feeds_by_role: dict[str, np.ndarray], output_roles: tuple[str, ...]) -> list[np.ndarray]:
        """Run with inputs keyed by role (cast to the model's declared dtypes); outputs in ``output_roles`` order."""
        feeds = {}
        for role, arr in feeds_by_role.items():
            name = self.inputs[role]
            feeds[name] = np.ascontiguousarray(np.asarray(arr).astype(self.input_dtypes[name], copy=False))
        try:
            return self.session.run([self.outputs[r] for r in output_roles], feeds)
        except Exception as exc:  # onnxruntime raises its own exception types
            raise ModelFileError(f"{self.path}: inference failed ({exc}); is this the expected export?") from exc


def default_providers() -> list[str]:
    """CUDA first when onnxruntime offers it, then CPU."""
    import onnxruntime as ort

    avail = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in avail] or ["CPUExecutionProvider"]


def _signature_text(inputs: tuple[TensorSpec, ...], outputs: tuple[TensorSpec, ...]) -> str:
    return (f"inputs [{'; '.join(s.describe() for s in inputs)}] -> "
            f"outputs [{'; '.join(s.describe() for s in outputs)}]")


def _bind(path: str, what: str, specs: tuple[TensorSpec, ...], actual: list[Any], expected: str) -> dict[str, str]:
    by_name = {a.name: a for a in actual}
    bound: dict[str, str] = {}
    for spec in specs:
        name = next((n for n in spec.names if n in by_name), None)
        if name is None and spec.names == ("*",) and len(actual) == 1:
            name = actual[0].name
        if name is None:
            if spec.required:
                raise ModelFileError(
                    f"{path}: no {what} named {'/'.join(spec.names)} (the model has {sorted(by_name)}); "
                    f"expected {expected}; re-export it as described in torm/segmentation/README.md"
                )
            continue
        shape = list(by_name[name].shape)
        if len(shape) != len(spec.dims):
            raise ModelFileError(f"{path}: {what} {name!r} has rank {len(shape)} {shape}, expected {spec.describe()}")
        for d_act, d_exp in zip(shape, spec.dims, strict=True):
            if d_exp is not None and isinstance(d_act, int) and d_act != d_exp:
                raise ModelFileError(f"{path}: {what} {name!r} has shape {shape}, expected {spec.describe()}")
        bound[spec.role] = name
    return bound


def session_threads(threads: int = 0) -> int:
    """onnxruntime intra-op threads for ``threads`` (0 = automatic): ``threads`` when > 0, else ``TORM_THREADS``
    when set (a benchmark worker's share of the cores, :func:`torm.runtime.free_cores`), else 0 (onnxruntime's own
    default: every physical core).

    Without this a benchmark's two workers each ran onnxruntime on both cores of a 2-core machine, idle threads
    spinning on the other worker's core: 4.6 s of segmentation per trial against 2.7 s with it
    (`benchmarks/results/throughput_realistic_v4fast{,_ort2}.md`, 2026-12-06)."""
    from torm.runtime import free_cores

    if threads > 0:
        return int(threads)
    return free_cores() if os.environ.get("TORM_THREADS") else 0


def open_session(
    path: str | Path,
    config_key: str,
    inputs: tuple[TensorSpec, ...],
    outputs: tuple[TensorSpec, ...],
    providers: list[str] | None = None,
    threads: int = 0,
    mem_arena: bool = True,
) -> BoundSession:
    """Load ``path`` with onnxruntime and bind its tensors to the expected signature.

    Raises ModelFileError when the path is unset or missing, the file is not a loadable ONNX model,
    an expected tensor is absent or has the wrong rank/static size, or the model needs an input that
    torm does not feed. ``mem_arena`` False: onnxruntime's CPU memory arena and memory-pattern planning are off
    (each tensor is freed when it dies: a lower peak for large graphs, at some speed).
    """
    import onnxruntime as ort

    expected = _signature_text(inputs, outputs)
    if not str(path):
        raise ModelFileError(f"{config_key} is not set; point it at an ONNX file with {expected} (`torm export-models "
                             "--out models/` writes them and a config YAML from local weight folders)")
    p = Path(path).expanduser()
    if not p.is_file():
        raise ModelFileError(f"{config_key} file {p} does not exist; expected an ONNX model with {expected} (`torm "
                             "export-models` writes one from local weight folders)")
    opts = ort.SessionOptions()
    threads = session_threads(threads)
    if threads > 0:
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        if threads < (os.cpu_count() or 1):  # sharing the machine: idle threads must not spin on the others' cores
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.log_severity_level = 3
    if not mem_arena:
        opts.enable_cpu_mem_arena = False
        opts.enable_mem_pattern = False
    try:
        sess = ort.InferenceSession(str(p), sess_options=opts, providers=providers or default_providers())
    except Exception as exc:
        raise ModelFileError(
            f"{config_key} file {p} cannot be loaded by onnxruntime ({exc}); expected {expected}") from exc
    where = f"{config_key} file {p}"
    in_bound = _bind(where, "input", inputs, sess.get_inputs(), expected)
    out_bound = _bind(where, "output", outputs, sess.get_outputs(), expected)
    extra = [a.name for a in sess.get_inputs() if a.name not in in_bound.values()]
    if extra:
        raise ModelFileError(
            f"{where}: the model needs input(s) {extra} that torm does not provide; expected {expected}")
    dtypes = {}
    for a in sess.get_inputs():
        if a.type not in _ORT_DTYPES:
            raise ModelFileError(f"{where}: input {a.name!r} has unsupported type {a.type}")
        dtypes[a.name] = _ORT_DTYPES[a.type]
    log.info("loaded %s on %s", p, sess.get_providers())
    return BoundSession(p, sess, in_bound, out_bound, dtypes)


def static_dims(bound: BoundSession, role: str) -> list[int | None]:
    """The static dims (int) or None (symbolic) of the input bound to ``role``."""
    name = bound.inputs[role]
    arg = next(a for a in bound.session.get_inputs() if a.name == name)
    return [d if isinstance(d, int) else None for d in arg.shape]
