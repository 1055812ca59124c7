"""A ``torm train-segmenter --finetune`` folder from simulated captures: each view's RGB and its glass-only mask.

Adapting a learned segmenter to a renderer (for instance the default MuJoCo rasteriser) uses the same few-shot tool
as adapting it to a user's real frames. This script writes ``<out>/images/<capture>_<view>.png`` and
``<out>/masks/<capture>_<view>.png`` (uint8 instance ids 1..N of the transparent objects, ``metadata
["transparent_ids"]``; opaque objects are background, as in every training recipe) for every view of every capture
folder matched by ``--captures`` (a glob), at most ``torm.segmentation.training.finetune.MAX_FRAMES`` views.

The 2026-12-06 MuJoCo experiment (``benchmarks/results/README.md``):
``python benchmarks/segmentation_reference.py --views 6 --renderer mujoco --seed-offset 300 --rows difference``
(renders and caches layouts 300-323), then
``python benchmarks/finetune_frames_from_captures.py --captures 'runs/seg_reference_captures/*_s3[0-9][0-9]_*_mujoco_*'
--out runs/ft_mj/frames`` and ``torm train-segmenter --finetune runs/ft_mj/frames --init
torm/segmentation/models/learned_seg_v4.onnx --work runs/ft_mj --out runs/ft_mj/learned_seg_v4mj.onnx``.
"""

from __future__ import annotations

import argparse
import glob
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

log = logging.getLogger("finetune_frames_from_captures")


def glass_instances(mask_hxw: np.ndarray, transparent_ids: list[int]) -> np.ndarray:
    """(H, W) uint8: the transparent objects of an instance mask renumbered 1..N in id order, everything else 0."""
    out = np.zeros(mask_hxw.shape, np.uint8)
    ids = sorted(int(k) for k in np.unique(mask_hxw) if k in set(transparent_ids))
    if len(ids) > 255:
        raise ValueError(f"{len(ids)} transparent objects in one view; a fine-tune mask holds at most 255")
    for new, k in enumerate(ids, start=1):
        out[mask_hxw == k] = new
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", required=True, help="a glob of capture folders (transforms.json inside)")
    ap.add_argument("--out", required=True, help="the fine-tune folder to write (images/, masks/)")
    args = ap.parse_args(argv)
    from torm.capture.io import load_capture
    from torm.segmentation.training.finetune import MAX_FRAMES

    folders = sorted(p for p in glob.glob(args.captures) if (Path(p) / "transforms.json").is_file())
    if not folders:
        raise SystemExit(f"no capture folder matches {args.captures!r}")
    caps = [(Path(f).name, load_capture(f)) for f in folders]
    n = sum(len(c) for _, c in caps)
    if n > MAX_FRAMES:
        raise SystemExit(f"{n} views in {len(caps)} captures; a fine-tune folder takes at most {MAX_FRAMES}: "
                         "match fewer captures")
    out = Path(args.out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "masks").mkdir(parents=True, exist_ok=True)
    for name, cap in caps:
        if "transparent_ids" not in cap.metadata:
            raise SystemExit(f"{name}: metadata has no transparent_ids (which objects are glass); capture it with "
                             "benchmarks/segmentation_reference.py or add them")
        for i, (view, mask) in enumerate(zip(cap.views, cap.masks(), strict=True)):
            if view.rgb is None:
                raise SystemExit(f"{name} view {i} has no RGB image")
            cv2.imwrite(str(out / "images" / f"{name}_{i}.png"), cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(out / "masks" / f"{name}_{i}.png"), glass_instances(mask, cap.metadata["transparent_ids"]))
    print(f"{n} frames from {len(caps)} captures in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
