"""COLMAP text model -> a ``transforms.json`` capture folder (the format :func:`torm.capture.io.load_capture` reads).

COLMAP's ``sparse/0/cameras.txt`` holds one line per camera, ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``
(models ``SIMPLE_PINHOLE f cx cy``, ``PINHOLE fx fy cx cy``, ``SIMPLE_RADIAL f cx cy k``, ``RADIAL f cx cy k1
k2``, ``OPENCV fx fy cx cy k1 k2 p1 p2``), and ``images.txt`` two lines per image, the first
``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``: the world-to-camera rotation (quaternion wxyz) and
translation in COLMAP's camera axes, which are OpenCV's (x right, y down, z forward). So
``T_world_cam = inv([R(q) | t])``; ``transform_matrix`` stores it in OpenGL axes as nerfstudio does.
Distortion coefficients are copied (``k1``, ``k2``, ``p1``, ``p2``); the loader warns that it ignores
them, so undistort the images first (``colmap image_undistorter``) for exact silhouettes.

COLMAP's units are arbitrary (a scale-free reconstruction): give ``scale`` (metres per COLMAP unit, e.g.
from a known distance) for metric meshes; the reconstruction itself needs no scale (automatic bounds).

Run: ``python -m torm.capture.colmap SPARSE_DIR --images IMAGES_DIR [--masks MASKS_DIR] --out CAPTURE_DIR``.
Masks are matched to images by file stem (``masks/<stem>.png``); the images are referenced, not copied.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import CaptureError
from torm.geometry import cv_to_gl, invert_T, make_T, quat_wxyz_to_R

#: Parameter names per COLMAP camera model (the pinhole part and the distortion part).
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise CaptureError(f"COLMAP model file {path} is missing; export the model as text (colmap model_converter "
                           "--output_type TXT)")
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def read_cameras(path: Path) -> dict[int, dict[str, Any]]:
    """``cameras.txt`` -> {camera id: {fl_x, fl_y, cx, cy, w, h, (k1, k2, p1, p2)}} in pixels."""
    out = {}
    for ln in _lines(path):
        tok = ln.split()
        cam_id, model, w, h = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
        if model not in CAMERA_MODELS:
            raise CaptureError(f"{path}: camera {cam_id} has model {model}; supported: {', '.join(CAMERA_MODELS)} "
                               "(undistort to PINHOLE with colmap image_undistorter)")
        p = dict(zip(CAMERA_MODELS[model], (float(x) for x in tok[4:]), strict=True))
        cam = {"fl_x": p.get("fx", p.get("f")), "fl_y": p.get("fy", p.get("f")), "cx": p["cx"], "cy": p["cy"],
               "w": w, "h": h}
        cam.update({k: p[k] for k in ("k1", "k2", "p1", "p2") if k in p})
        out[cam_id] = cam
    return out


def read_images(path: Path) -> list[tuple[str, int, np.ndarray]]:
    """``images.txt`` -> [(image name, camera id, T_world_cam (4, 4) OpenCV axes)], sorted by name."""
    lines = _lines(path)
    out = []
    for ln in lines:
        tok = ln.split()
        if len(tok) < 10:
            continue  # a 2-D points line
        try:
            q = np.array([float(x) for x in tok[1:5]])
            t = np.array([float(x) for x in tok[5:8]])
            cam_id = int(tok[8])
        except ValueError:
            continue  # a 2-D points line that happens to have >= 10 tokens
        T_cam_world = make_T(quat_wxyz_to_R(q / np.linalg.norm(q)), t)
        out.append((" ".join(tok[9:]), cam_id, invert_T(T_cam_world)))
    if not out:
        raise CaptureError(f"{path}: no image poses found")
    return sorted(out)


def colmap_to_transforms(sparse_dir: str | Path, images_dir: str | Path, out_dir: str | Path,
                         masks_dir: str | Path | None = None, scale: float = 1.0) -> Path:
    """Write ``out_dir/transforms.json`` for a COLMAP text model; returns its path (see the module docstring)."""
    sparse, images, out = Path(sparse_dir), Path(images_dir), Path(out_dir)
    cams = read_cameras(sparse / "cameras.txt")
    frames = []
    for name, cam_id, T in read_images(sparse / "images.txt"):
        if cam_id not in cams:
            raise CaptureError(f"{sparse / 'images.txt'}: image {name} uses camera {cam_id}, not in cameras.txt")
        T = T.copy()
        T[:3, 3] *= scale
        img = images / name
        frame: dict[str, Any] = {"file_path": os.path.relpath(img, out), "transform_matrix": cv_to_gl(T).tolist(),
                                 **cams[cam_id]}
        if masks_dir is not None:
            m = Path(masks_dir) / (Path(name).stem + ".png")
            if not m.is_file():
                raise CaptureError(f"mask {m} for image {name} is missing; masks are matched by file stem")
            frame["mask_path"] = os.path.relpath(m, out)
        frames.append(frame)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "transforms.json"
    path.write_text(json.dumps({"camera_model": "PINHOLE", "frames": frames,
                                "metadata": {"source": "colmap", "scale_m_per_unit": scale}}, indent=1))
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("sparse", help="COLMAP text model folder (cameras.txt, images.txt)")
    p.add_argument("--images", required=True, help="folder of the images named in images.txt")
    p.add_argument("--masks", default=None, help="folder of masks named <image stem>.png")
    p.add_argument("--out", required=True, help="capture folder to write transforms.json into")
    p.add_argument("--scale", type=float, default=1.0, help="metres per COLMAP unit")
    a = p.parse_args(argv)
    print(json.dumps({"transforms": str(colmap_to_transforms(a.sparse, a.images, a.out, a.masks, a.scale))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["CAMERA_MODELS", "colmap_to_transforms", "read_cameras", "read_images"]
