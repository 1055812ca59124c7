"""``torm train-segmenter``: reproduce the learned segmenter (render data, train, export ONNX, evaluate).

Examples (the shipped recipe into runs/seg_train/; PBR renders overwriting the shipped model; a tiny run)::

    torm train-segmenter
    torm train-segmenter --renderer pbr --install
    torm train-segmenter --set train.steps=20 --set data.shards.train=1 --out /tmp/tiny.onnx
    torm train-segmenter --finetune my_frames/ --out runs/my_seg.onnx     # few-shot on your labelled real frames

``--finetune DIR`` adapts a trained model (``--init``, default the shipped one) to a handful of your own labelled
frames (``DIR/images/<name>.jpg`` + ``DIR/masks/<name>.png``, or ``<name>.jpg`` + ``<name>-mask.png``; masks from
any tool, 0 = background) in ``--steps`` steps (default 300, about 4 minutes on 2 cores, plus about 1.5 minutes to
render the rehearsal views once: ``--rehearsal-shards``, renders of the base model's own recipe that fill half of
every batch) and writes the ONNX file and its card (which frames it saw); use it with ``--segmenter learned --set
model=runs/my_seg.onnx``.

Stages resume: rendered shards (``--data``, default ``runs/seg_data/<renderer>``) are kept, training continues
from ``--work``'s checkpoint. Writes the ONNX file and its model card (same name, ``.json``: training config,
data recipe, held-out shapes, time, held-out metrics). ``--config`` is YAML with ``data:`` and ``train:``
sections (fields of ``DataRecipe`` / ``TrainConfig``); ``--set data.x=...`` / ``--set train.x=...`` override
(``torm config show train-segmenter`` lists every key).
Prints the model card's summary as JSON.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from torm.commands._common import add_overrides, add_parser, check_output_dir, check_output_file, count_arg, print_json

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "train-segmenter", __doc__,
                   help="render data, train, export and evaluate the learned segmenter")
    p.add_argument("--renderer", choices=("mujoco", "pbr"), default=None, help="dataset renderer (default: recipe's)")
    p.add_argument("--data", default=None, help="shard folder (default runs/seg_data/<renderer>)")
    p.add_argument("--work", default="runs/seg_train", help="training folder (checkpoints)")
    p.add_argument("--out", default=None, help="ONNX output (default <work>/learned_seg.onnx)")
    p.add_argument("--install", action="store_true", help="write the ONNX + card into the package (models/)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: train.threads)")
    p.add_argument("--workers", type=count_arg, default=1,
                   help="processes rendering missing shards, one core each (the data do not depend on it)")
    p.add_argument("--no-eval", dest="evaluate", action="store_false", help="skip the held-out evaluation")
    p.add_argument("--export-only", action="store_true",
                   help="no more training steps: export the best checkpoint of --work as it stands (resume later)")
    p.add_argument("--finetune", default=None, metavar="DIR",
                   help="few-shot: fine-tune --init on the labelled frames in DIR (no rendering)")
    p.add_argument("--init", default="", help="--finetune: the model to start from (default: the shipped one)")
    p.add_argument("--steps", type=count_arg, default=300, help="--finetune: training steps (default 300)")
    p.add_argument("--rehearsal-shards", type=int, default=4,
                   help="--finetune: shards (16 views each) of the base model's own recipe rendered and mixed into "
                        "half of every batch so your frames do not erase what it knew (default 4; 0 = none)")
    add_overrides(p, example="train.steps=20", target="train-segmenter")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torm import config as cfgmod
    from torm.segmentation.learned import DEFAULT_MODEL
    from torm.segmentation.training.run import SegTrainingSpec
    from torm.segmentation.training.run import run as run_training

    if args.finetune:
        return _finetune(args)
    overrides = list(args.overrides)
    if args.renderer:
        overrides.append(f"data.renderer={args.renderer}")
    if args.threads:
        overrides.append(f"train.threads={args.threads}")
    data = cfgmod.load_yaml(args.config) if args.config else {}
    spec = cfgmod.from_dict(SegTrainingSpec, data, overrides, where=str(args.config or "train-segmenter"))
    data_dir = Path(args.data) if args.data else Path("runs/seg_data") / spec.data.renderer
    out = DEFAULT_MODEL if args.install else Path(args.out) if args.out else Path(args.work) / "learned_seg.onnx"
    check_output_file(out)  # a file on the way or an unwritable place: refused before hours of rendering
    check_output_dir(Path(args.work), "--work")
    card = run_training(spec, data_dir, Path(args.work), out, evaluate_after=args.evaluate,
                        export_only=args.export_only, workers=args.workers)
    print_json({"out": str(out), "card": str(out.with_suffix(".json")), "training": card["training"],
                "held_out_metrics": {k: {m: v.get(m) for m in ("silhouette_iou_mean", "object", "held_out_objects")}
                                     for k, v in card.get("held_out_metrics", {}).items() if isinstance(v, dict)}})
    return 0


def _finetune(args: argparse.Namespace) -> int:
    from torm.segmentation.training.finetune import finetune

    out = Path(args.out) if args.out else Path(args.work) / "learned_seg_finetuned.onnx"
    check_output_file(out)
    card = finetune(args.finetune, out, base_model=args.init, steps=args.steps, threads=args.threads or 1,
                    rehearsal_shards=args.rehearsal_shards, rehearsal_data=Path(args.work) / "rehearsal")
    print_json({"out": str(out), "card": str(out.with_suffix(".json")), "frames": len(card["finetune"]["frames"]),
                "training": card["training"], "use": f"--segmenter learned --set model={out}"})
    return 0
