"""``torm calibrate``: calibrations for the real robot.

- ``torm calibrate hand-eye``: eye-in-hand calibration of the wrist camera from ChArUco board images and
  the robot pose of each image. Writes ``T_flange_cam`` (4x4, m, OpenCV camera axes) to ``--out`` and prints
  JSON with the residuals (spread of the board's base-frame pose over the images: translation mm, rotation deg).

  ``--poses`` (YAML/JSON): ``poses: [{image: 000.png, q: [6 joint values, rad]}, ...]`` or with
  ``T_base_flange: 4x4`` instead of ``q``; joint values use the robot config's flange site for FK.
  ``--intrinsics`` (YAML/JSON): ``K`` (3x3) or ``fx, fy, cx, cy``, optional ``dist`` [k1, k2, p1, p2, k3]
  (e.g. the D455 colour stream's; use zeros for images already undistorted).

Example::

    torm calibrate hand-eye --images calib/images --poses calib/poses.yaml --intrinsics calib/d455.yaml \\
        --board 7x5 --square 0.03 --marker 0.022 --out hand_eye.yaml
"""

from __future__ import annotations

import argparse

from torm.commands._common import add_parser, add_robot, check_output_file, positive_float, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "calibrate", __doc__, help="real-robot calibrations (hand-eye)")
    sub = p.add_subparsers(dest="calibrate_command", metavar="ACTION", required=True)
    he = sub.add_parser("hand-eye", help="eye-in-hand calibration from ChArUco images + robot poses")
    he.add_argument("--images", required=True, help="folder with the board images")
    he.add_argument("--poses", required=True, help="YAML/JSON with the robot pose of every image")
    he.add_argument("--intrinsics", required=True, help="YAML/JSON with K (or fx, fy, cx, cy) and optional dist")
    he.add_argument("--board", default="7x5", help="squares across x down (default 7x5)")
    he.add_argument("--square", type=positive_float, default=0.03, help="square side in metres (default 0.03)")
    he.add_argument("--marker", type=positive_float, default=0.022, help="marker side in metres (default 0.022)")
    he.add_argument("--dict", dest="dictionary", default="DICT_5X5_100", help="ArUco dictionary (default DICT_5X5_100)")
    he.add_argument("--method", default="PARK", help="TSAI | PARK | HORAUD | ANDREFF | DANIILIDIS (default PARK)")
    add_robot(he, "inovo_2f85")
    he.add_argument("--out", required=True, help="output hand-eye YAML")
    he.set_defaults(func=run_hand_eye)


def _flange_fk(robot: str):
    import mujoco
    import numpy as np

    from sim.robots.config import load_robot_config

    rcfg = load_robot_config(robot)
    model = rcfg.robot_model()  # composed like in the world, base at base_pose
    data = mujoco.MjData(model)
    ids = rcfg.resolve(model)
    qadr, sid = ids.arm_qadr, ids.flange_site

    def fk(q):
        data.qpos[qadr] = q
        mujoco.mj_kinematics(model, data)
        T = np.eye(4)
        T[:3, :3] = data.site_xmat[sid].reshape(3, 3)
        T[:3, 3] = data.site_xpos[sid]
        return T

    return fk


def run_hand_eye(args: argparse.Namespace) -> int:
    from torm.hardware.handeye import (
        CharucoSpec,
        calibrate_from_images,
        load_intrinsics,
        load_poses,
        save_hand_eye,
    )

    check_output_file(args.out)  # before any image is read
    spec = CharucoSpec.parse(args.board, args.square, args.marker, args.dictionary)
    K, dist = load_intrinsics(args.intrinsics)
    cache: dict = {}

    def fk(q):  # the robot model is loaded only when the poses file gives joint values
        if "fk" not in cache:
            cache["fk"] = _flange_fk(args.robot_config)
        return cache["fk"](q)

    poses = load_poses(args.poses, fk)
    res = calibrate_from_images(args.images, poses, K, dist, spec, args.method)
    summary = res.residuals.summary()
    save_hand_eye(args.out, res.T_flange_cam, args.method.upper(), summary, len(res.used))
    print_json({"out": args.out, "method": args.method.upper(), "T_flange_cam": res.T_flange_cam,
                "residuals": summary, "used": list(res.used), "skipped": list(res.skipped)})
    return 0
