"""COLMAP sparse model (text or binary) -> a ``transforms.json`` capture folder (what ``load_capture`` reads).

COLMAP's ``sparse/0/cameras.txt`` holds one line per camera, ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``
(models ``SIMPLE_PINHOLE f cx cy``, ``PINHOLE fx fy cx cy``, ``SIMPLE_RADIAL f cx cy k``, ``RADIAL f cx cy k1
k2``, ``OPENCV fx fy cx cy k1 k2 p1 p2``, ``OPENCV_FISHEYE fx fy cx cy k1 k2 k3 k4``), and ``images.txt`` two
lines per image, the first ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``: the world-to-camera rotation
(quaternion wxyz) and translation in COLMAP's camera axes, which are OpenCV's (x right, y down, z forward). So
``T_world_cam = inv([R(q) | t])``; ``transform_matrix`` stores it in OpenGL axes as nerfstudio does. The binary
files (``cameras.bin``, ``images.bin``; COLMAP's default output) hold the same records (``read_model`` picks
whichever is there). Each frame gets its camera's ``camera_model`` and coefficients, and the loader undoes the
distortion (:mod:`torm.capture.lens`); other COLMAP models (FULL_OPENCV, FOV, the radial fisheyes) are a named
error: undistort with ``colmap image_undistorter`` first.

COLMAP's units are arbitrary (a scale-free reconstruction): give ``scale`` (metres per COLMAP unit, e.g.
from a known distance) for metric meshes; the reconstruction itself needs no scale (automatic bounds).

Run: ``torm import colmap SPARSE_DIR --images IMAGES_DIR [--masks MASKS_DIR] --out CAPTURE_DIR`` (or
``python -m torm.capture.colmap ...``). Masks are matched to images by file stem (``masks/<stem>.png``); the
images are referenced, not copied. :func:`write_model` writes a capture's cameras as a COLMAP model (text or
binary): the other direction, and what the round-trip test uses.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
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
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
#: COLMAP's model ids (``colmap/src/colmap/sensor/models.h``) and parameter counts, for the binary format
MODEL_IDS: dict[int, tuple[str, int]] = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4),
                                         3: ("RADIAL", 5), 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8),
                                         6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
                                         9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}
_DIST = ("k1", "k2", "k3", "k4", "p1", "p2")


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise CaptureError(f"COLMAP model file {path} is missing; export the model as text (colmap model_converter "
                           "--output_type TXT)")
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def _camera(path: Path, cam_id: int, model: str, w: int, h: int, params: list[float]) -> dict[str, Any]:
    if model not in CAMERA_MODELS:
        raise CaptureError(f"{path}: camera {cam_id} has model {model}; supported: {', '.join(CAMERA_MODELS)} "
                           "(undistort to PINHOLE with colmap image_undistorter)")
    if len(params) != len(CAMERA_MODELS[model]):
        raise CaptureError(f"{path}: camera {cam_id} ({model}) has {len(params)} parameters, expected "
                           f"{len(CAMERA_MODELS[model])}: {' '.join(CAMERA_MODELS[model])}")
    p = dict(zip(CAMERA_MODELS[model], params, strict=True))
    cam = {"fl_x": p.get("fx", p.get("f")), "fl_y": p.get("fy", p.get("f")), "cx": p["cx"], "cy": p["cy"],
           "w": w, "h": h, "camera_model": "PINHOLE" if model in ("PINHOLE", "SIMPLE_PINHOLE") else model}
    cam.update({k: p[k] for k in _DIST if k in p})
    return cam


def read_cameras(path: Path) -> dict[int, dict[str, Any]]:
    """``cameras.txt`` or ``cameras.bin`` -> {camera id: {fl_x, fl_y, cx, cy, w, h, camera_model, (k1, ...)}} in
    pixels."""
    path = Path(path)
    if path.suffix == ".bin":
        return _read_cameras_bin(path)
    out = {}
    for ln in _lines(path):
        tok = ln.split()
        cam_id, model, w, h = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
        out[cam_id] = _camera(path, cam_id, model, w, h, [float(x) for x in tok[4:]])
    return out


def _read_cameras_bin(path: Path) -> dict[int, dict[str, Any]]:
    if not path.is_file():
        raise CaptureError(f"COLMAP model file {path} is missing")
    data = path.read_bytes()
    try:
        (n,) = struct.unpack_from("<Q", data, 0)
        off, out = 8, {}
        for _ in range(n):
            cam_id, model_id, w, h = struct.unpack_from("<iiQQ", data, off)
            off += 24
            if model_id not in MODEL_IDS:
                raise CaptureError(f"{path}: camera {cam_id} has unknown model id {model_id}")
            model, n_par = MODEL_IDS[model_id]
            params = list(struct.unpack_from(f"<{n_par}d", data, off))
            off += 8 * n_par
            out[cam_id] = _camera(path, cam_id, model, int(w), int(h), params)
    except struct.error as exc:
        raise CaptureError(f"{path}: truncated or not a COLMAP cameras.bin ({exc})") from exc
    return out


def _read_images_bin(path: Path) -> list[tuple[str, int, np.ndarray]]:
    if not path.is_file():
        raise CaptureError(f"COLMAP model file {path} is missing")
    data = path.read_bytes()
    out = []
    try:
        (n,) = struct.unpack_from("<Q", data, 0)
        off = 8
        for _ in range(n):
            _img_id, qw, qx, qy, qz, tx, ty, tz, cam_id = struct.unpack_from("<idddddddi", data, off)
            off += 64
            end = data.index(b"\x00", off)
            name = data[off:end].decode("utf-8")
            off = end + 1
            (n_pts,) = struct.unpack_from("<Q", data, off)
            off += 8 + 24 * n_pts
            q = np.array([qw, qx, qy, qz])
            out.append((name, int(cam_id), invert_T(make_T(quat_wxyz_to_R(q / np.linalg.norm(q)),
                                                            np.array([tx, ty, tz])))))
    except (struct.error, ValueError) as exc:
        raise CaptureError(f"{path}: truncated or not a COLMAP images.bin ({exc})") from exc
    if not out:
        raise CaptureError(f"{path}: no image poses found")
    return sorted(out)


def model_files(sparse_dir: str | Path) -> tuple[Path, Path]:
    """(cameras, images) files of a COLMAP sparse model folder: the ``.bin`` pair, else the ``.txt`` pair."""
    d = Path(sparse_dir)
    for ext in (".bin", ".txt"):
        if (d / f"cameras{ext}").is_file() and (d / f"images{ext}").is_file():
            return d / f"cameras{ext}", d / f"images{ext}"
    if (d / "0").is_dir():
        return model_files(d / "0")
    raise CaptureError(f"{d} holds no COLMAP model (cameras.bin + images.bin, or cameras.txt + images.txt); point "
                       "at the sparse/0 folder")


def read_images(path: Path) -> list[tuple[str, int, np.ndarray]]:
    """``images.txt`` or ``images.bin`` -> [(image name, camera id, T_world_cam (4, 4) OpenCV axes)], sorted by
    name."""
    path = Path(path)
    if path.suffix == ".bin":
        return _read_images_bin(path)
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
    """Write ``out_dir/transforms.json`` for a COLMAP model (text or binary); returns its path (see the module
    docstring)."""
    images, out = Path(images_dir), Path(out_dir)
    cam_file, img_file = model_files(sparse_dir)
    cams = read_cameras(cam_file)
    frames = []
    for name, cam_id, T in read_images(img_file):
        if cam_id not in cams:
            raise CaptureError(f"{img_file}: image {name} uses camera {cam_id}, not in {cam_file.name}")
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
    path.write_text(json.dumps({"frames": frames, "metadata": {"source": "colmap", "scale_m_per_unit": scale,
                                                               "model": str(cam_file.parent)}}, indent=1))
    return path


def write_model(capture: Any, folder: str | Path, binary: bool = False, names: list[str] | None = None,
                lens: dict[str, float] | None = None, camera_model: str = "PINHOLE") -> tuple[Path, Path]:
    """Write ``capture``'s cameras (one COLMAP camera per view, poses world-to-camera) as a COLMAP sparse model in
    ``folder`` (``cameras.txt``/``images.txt``, or ``.bin`` with ``binary``); image names ``names`` (default
    ``00000.png``...). ``camera_model`` and ``lens`` (its coefficients by name) describe the images' distortion.
    Returns the two file paths."""
    from torm.geometry import R_to_quat_wxyz

    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    if camera_model not in CAMERA_MODELS:
        raise CaptureError(f"camera_model {camera_model!r}; valid choices: {', '.join(CAMERA_MODELS)}")
    H, W = capture.image_size
    names = names or [f"{i:05d}.png" for i in range(len(capture))]
    lens = lens or {}
    cams, imgs = [], []
    for i, v in enumerate(capture.views):
        K = v.K
        vals = {"f": K[0, 0], "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
        params = [float(vals.get(k, lens.get(k, 0.0))) for k in CAMERA_MODELS[camera_model]]
        cams.append((i + 1, camera_model, W, H, params))
        T = invert_T(v.T_world_cam)
        imgs.append((i + 1, R_to_quat_wxyz(T[:3, :3]), T[:3, 3], i + 1, names[i]))
    if binary:
        ids = {m: k for k, (m, _) in MODEL_IDS.items()}
        cb = struct.pack("<Q", len(cams)) + b"".join(
            struct.pack("<iiQQ", c, ids[m], w, h) + struct.pack(f"<{len(p)}d", *p) for c, m, w, h, p in cams)
        ib = struct.pack("<Q", len(imgs)) + b"".join(
            struct.pack("<idddddddi", k, *map(float, q), *map(float, t), c) + n.encode() + b"\x00"
            + struct.pack("<Q", 0) for k, q, t, c, n in imgs)
        (d / "cameras.bin").write_bytes(cb)
        (d / "images.bin").write_bytes(ib)
        return d / "cameras.bin", d / "images.bin"
    (d / "cameras.txt").write_text("# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
        f"{c} {m} {w} {h} {' '.join(repr(x) for x in p)}\n" for c, m, w, h, p in cams))
    (d / "images.txt").write_text("# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n" + "".join(
        f"{k} {' '.join(repr(float(x)) for x in q)} {' '.join(repr(float(x)) for x in t)} {c} {n}\n\n"
        for k, q, t, c, n in imgs))
    return d / "cameras.txt", d / "images.txt"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("sparse", help="COLMAP model folder (cameras.bin + images.bin, or the .txt pair)")
    p.add_argument("--images", required=True, help="folder of the images named in images.txt")
    p.add_argument("--masks", default=None, help="folder of masks named <image stem>.png")
    p.add_argument("--out", required=True, help="capture folder to write transforms.json into")
    p.add_argument("--scale", type=float, default=1.0, help="metres per COLMAP unit")
    a = p.parse_args(argv)
    print(json.dumps({"transforms": str(colmap_to_transforms(a.sparse, a.images, a.out, a.masks, a.scale))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["CAMERA_MODELS", "MODEL_IDS", "colmap_to_transforms", "model_files", "read_cameras", "read_images",
           "write_model"]
