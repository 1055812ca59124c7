"""``torm import``: bring a capture made elsewhere into torm's format (``transforms.json`` + masks).

Examples::

    torm import colmap scan/sparse/0 --images scan/images --masks scan/masks --out runs/scan
    torm import colmap scan/sparse --images scan/images --out runs/scan --scale 0.001

``colmap SPARSE_DIR``: a COLMAP sparse model, binary (``cameras.bin``, ``images.bin``: COLMAP's default) or text
(``.txt``); ``sparse/`` holding a ``0/`` folder works too. Cameras SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
OPENCV and OPENCV_FISHEYE keep their model and coefficients per frame, and ``torm reconstruct`` / ``torm segment``
undo the distortion when they load the folder; other COLMAP models are refused (undistort with
``colmap image_undistorter``). ``--scale``: metres per COLMAP unit (COLMAP has no scale). Masks are matched to
images by file stem (``MASKS/<stem>.png``); images and masks are referenced, not copied. Prints the path of the
written ``transforms.json`` and the number of frames as JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from torm.commands._common import add_overrides, add_parser, check_output_dir, positive_float, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "import", __doc__, help="bring a capture made elsewhere (COLMAP) into torm's format")
    sub = p.add_subparsers(dest="source", required=True, metavar="SOURCE")
    c = add_parser(sub, "colmap", __doc__, help="a COLMAP sparse model (binary or text) -> transforms.json")
    c.add_argument("sparse", metavar="SPARSE_DIR", help="COLMAP model folder (cameras/images .bin or .txt)")
    c.add_argument("--images", required=True, help="folder of the images named in the model")
    c.add_argument("--masks", default=None, help="folder of masks named <image stem>.png (optional)")
    c.add_argument("--out", required=True, help="capture folder to write transforms.json into")
    c.add_argument("--scale", type=positive_float, default=1.0, help="metres per COLMAP unit (default 1)")
    add_overrides(c, example="scale=0.001", target="import colmap (its options)")
    c.set_defaults(func=run_colmap)


def run_colmap(args: argparse.Namespace) -> int:
    from torm.capture.colmap import colmap_to_transforms
    from torm.errors import ConfigError

    if not args.scale > 0:
        raise ConfigError(f"--scale {args.scale} must be > 0 (metres per COLMAP unit)")
    out = check_output_dir(args.out)
    path = colmap_to_transforms(args.sparse, args.images, out, args.masks, args.scale)
    doc = json.loads(Path(path).read_text())
    models = sorted({f.get("camera_model", "PINHOLE") for f in doc["frames"]})
    print_json({"transforms": str(path), "frames": len(doc["frames"]), "camera_models": models})
    return 0
