"""Synthetic "recorded frames": NeRF-style capture folders of known meshes, as a user would bring them.

Each case (:data:`RECORDED_CASES`) writes a folder in the nerfstudio/NeRF ``transforms.json`` convention
(``camera_angle_x``, ``w``, ``h``, per-frame ``file_path`` and OpenGL camera-to-world ``transform_matrix``)
with **no** ``workspace_bounds`` and **no** ``table_height``, and masks as a segmenter or a matting tool
writes them: soft 8-bit greyscale PNGs (``mask_path``; edge pixels hold their coverage, 0..255) or the
alpha channel of RGBA images. Objects need not stand on z = 0: some hang below it, some are cut by the
image border in some views. The meshes are returned as ground truth (metres, world frame).

Silhouettes are rendered with :func:`torm.reconstruction.raster.render_mask` at 4x supersampling and
area-averaged, so a mask pixel's value is the fraction of it the objects cover. The images are flat
colours (objects darker than the background); only the masks matter for reconstruction.

Run ``python -m torm.capture.synthetic_frames OUT [CASE]`` to write one (README: "reconstruct your own capture").
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torm.geometry import cv_to_gl, look_at_cv
from torm.types import TriMesh

#: The cases: objects (trimesh primitive, size parameters in m, centre xyz in m), camera ring, image size.
RECORDED_CASES: dict[str, dict[str, Any]] = {
    "ring8": {
        "description": "10 views (8 input + 2 held out) at 320x240, a torus and a box, half of the torus below "
                       "z = 0, no table, soft greyscale masks, the box cut by the image border in 3 views",
        "objects": [("torus", (0.05, 0.018), (0.0, 0.0, 0.0)), ("box", (0.05, 0.04, 0.07), (0.0, 0.14, 0.02))],
        "n_views": 10, "hw": (240, 320), "fov_x_deg": 60.0, "radius": 0.42, "elevations_deg": (-25.0, 55.0),
        "aim_offset": [(3, (-0.08, -0.12, 0.0)), (6, (-0.08, -0.12, 0.0)), (9, (-0.08, -0.12, 0.0))], "alpha": False,
    },
    "glass10": {
        "description": "12 views (10 input + 2 held out) at 480x360, one capsule standing on z = 0 plus a "
                       "cylinder below it (a stand), no table given, soft alpha masks in RGBA images",
        "objects": [("capsule", (0.03, 0.08), (0.0, 0.0, 0.07)), ("cylinder", (0.045, 0.03), (0.0, 0.0, -0.02))],
        "n_views": 12, "hw": (360, 480), "fov_x_deg": 50.0, "radius": 0.45, "elevations_deg": (10.0, 50.0),
        "aim_offset": [], "alpha": True,
    },
    "bottles20": {
        "description": "20 views (16 input + 4 held out) at 640x480, a bottle-like cylinder, a capsule and a box "
                       "standing on z = 0 side by side, no table given, soft greyscale masks (a validation case: "
                       "not used to choose any default)",
        "objects": [("cylinder", (0.035, 0.14), (-0.06, -0.03, 0.07)), ("capsule", (0.022, 0.05), (0.05, -0.04, 0.047)),
                    ("box", (0.05, 0.07, 0.09), (0.0, 0.08, 0.045))],
        "n_views": 20, "hw": (480, 640), "fov_x_deg": 55.0, "radius": 0.55, "elevations_deg": (15.0, 60.0),
        "aim_offset": [], "alpha": False,
    },
    "dense100": {
        "description": "100 views (80 input + 20 held out) at 200x200 on a sphere around a torus knot-like "
                       "shape (two interlocked tori), exact soft masks",
        "objects": [("torus", (0.045, 0.012), (0.0, 0.0, 0.0)), ("torus_x", (0.045, 0.012), (0.045, 0.0, 0.0))],
        "n_views": 100, "hw": (200, 200), "fov_x_deg": 40.0, "radius": 0.5, "elevations_deg": (-60.0, 75.0),
        "aim_offset": [], "alpha": False,
    },
}


def _primitive(kind: str, size: tuple[float, ...], centre: tuple[float, float, float]) -> TriMesh:
    import trimesh

    if kind == "torus":
        m = trimesh.creation.torus(major_radius=size[0], minor_radius=size[1], major_sections=64, minor_sections=24)
    elif kind == "torus_x":  # a torus in the x-z plane (interlocks with one in the x-y plane)
        m = trimesh.creation.torus(major_radius=size[0], minor_radius=size[1], major_sections=64, minor_sections=24)
        m.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    elif kind == "box":
        m = trimesh.creation.box(extents=size)
    elif kind == "capsule":
        m = trimesh.creation.capsule(radius=size[0], height=size[1], count=[32, 32])
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=size[0], height=size[1], sections=64)
    else:  # pragma: no cover - the table above is fixed
        raise ValueError(kind)
    m.apply_translation(centre)
    return TriMesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64))


def case_meshes(case: str) -> list[TriMesh]:
    """The ground-truth meshes (m, world frame) of a case."""
    return [_primitive(k, s, c) for k, s, c in RECORDED_CASES[case]["objects"]]


def case_cameras(case: str, n_views: int | None = None, hw: tuple[int, int] | None = None
                 ) -> tuple[np.ndarray, list[np.ndarray]]:
    """(K (3, 3), camera-to-world poses in OpenCV axes) of a case: a spiral of views looking at the centre.
    ``n_views`` and ``hw`` (H, W px) replace the case's own (same field of view, same spiral)."""
    c = RECORDED_CASES[case]
    H, W = hw or c["hw"]
    f = (W / 2) / math.tan(math.radians(c["fov_x_deg"]) / 2)
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    n = n_views or c["n_views"]
    lo, hi = (math.radians(x) for x in c["elevations_deg"])
    offsets = dict(c["aim_offset"])
    centre = np.mean([np.asarray(o[2]) for o in c["objects"]], axis=0)
    golden = math.pi * (3 - math.sqrt(5))
    poses = []
    for i in range(n):
        el = lo + (hi - lo) * (i + 0.5) / n
        az = golden * i * 3.0
        eye = centre + c["radius"] * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        target = centre + np.asarray(offsets.get(i, (0.0, 0.0, 0.0)))
        poses.append(look_at_cv(eye, target))
    return K, poses


def soft_silhouette(meshes: list[TriMesh], K: np.ndarray, T_world_cam: np.ndarray, hw: tuple[int, int],
                    ss: int = 4) -> np.ndarray:
    """(H, W) float32 coverage in [0, 1] of the union of ``meshes`` (``ss`` x ``ss`` supersampling)."""
    from torm.reconstruction.raster import render_mask

    H, W = hw
    Ks = np.diag([ss, ss, 1.0]) @ K
    T_cw = np.linalg.inv(T_world_cam)
    hard = np.zeros((H * ss, W * ss), dtype=bool)
    for m in meshes:
        hard |= render_mask(m.verts_vx3, m.faces_fx3, Ks, T_cw, H * ss, W * ss)
    return cv2.resize(hard.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)


def write_recorded_capture(folder: str | Path, case: str = "ring8") -> list[TriMesh]:
    """Write the case's NeRF-style capture folder (see the module docstring); returns the GT meshes."""
    if case not in RECORDED_CASES:
        raise KeyError(f"unknown recorded case {case!r}; valid: {', '.join(RECORDED_CASES)}")
    c = RECORDED_CASES[case]
    root = Path(folder)
    (root / "images").mkdir(parents=True, exist_ok=True)
    meshes = case_meshes(case)
    K, poses = case_cameras(case)
    H, W = c["hw"]
    frames = []
    for i, T in enumerate(poses):
        cov = soft_silhouette(meshes, K, T, (H, W))
        grey = np.round(255 * cov).astype(np.uint8)
        rgb = np.full((H, W, 3), 200, np.uint8)
        rgb = (rgb * (1 - 0.6 * cov[..., None])).astype(np.uint8)
        frame: dict[str, Any] = {"transform_matrix": cv_to_gl(T).tolist()}
        if c["alpha"]:
            frame["file_path"] = f"./images/r_{i}"  # NeRF-synthetic style: no extension, RGBA with alpha
            cv2.imwrite(str(root / "images" / f"r_{i}.png"), np.dstack([rgb[..., ::-1], grey]))
        else:
            (root / "masks").mkdir(exist_ok=True)
            frame["file_path"] = f"images/{i:03d}.png"
            frame["mask_path"] = f"masks/{i:03d}.png"
            cv2.imwrite(str(root / frame["file_path"]), rgb[..., ::-1])
            cv2.imwrite(str(root / frame["mask_path"]), grey)
        frames.append(frame)
    doc = {"camera_angle_x": 2 * math.atan(W / (2 * K[0, 0])), "w": W, "h": H, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(doc, indent=1))
    return meshes


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args:
        print(f"usage: python -m torm.capture.synthetic_frames OUT [CASE]; cases: {', '.join(RECORDED_CASES)}",
              file=sys.stderr)
        return 2
    case = args[1] if len(args) > 1 else "ring8"
    write_recorded_capture(args[0], case)
    print(json.dumps({"folder": args[0], "case": case, "description": RECORDED_CASES[case]["description"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["RECORDED_CASES", "case_cameras", "case_meshes", "soft_silhouette", "write_recorded_capture"]
