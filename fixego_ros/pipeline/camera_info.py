"""Intrinsics from sensor_msgs/CameraInfo (ROS-free, duck-typed: rclpy and rosbags messages alike).

DESIGN.md §3: camera_info is optional when the rig file gives intrinsics. So a rig file may leave a camera's
intrinsics out; the nodes that need them (and ``fixego replay``) then take them from the camera's first
CameraInfo (plumb_bob: K, D, width, height) before using its images. When both exist and disagree (image size,
fx/fy/cx/cy by more than :data:`~fixego_ros.geometry.rig.PX_TOL` px, a distortion coefficient by more than
:data:`~fixego_ros.geometry.rig.DIST_TOL`), the rig file wins and the disagreement is reported (one error
naming both values). Only a camera's first CameraInfo is examined: a driver publishes the same one with every
image.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fixego_ros.geometry.rig import DIST_TOL, PX_TOL, SIDES, CameraModel, Rig, RigError, camera_model

CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
PLUMB_BOB = ('plumb_bob', '')      # '' : drivers that leave the model empty with D all zeros or empty


def camera_from_info(msg: Any, where: str = 'camera_info') -> CameraModel:
    """The :class:`CameraModel` of a CameraInfo; RigError (a ValueError) saying why it cannot be one."""
    model = str(getattr(msg, 'distortion_model', ''))
    d = [float(x) for x in getattr(msg, 'd', [])]
    k = [float(x) for x in getattr(msg, 'k', [])]
    if model not in PLUMB_BOB or (model == '' and any(d)):
        raise RigError(f"{where}: distortion_model {model!r} is not supported (plumb_bob only)")
    if len(k) != 9 or not np.all(np.isfinite(k)) or k[0] == 0.0:
        raise RigError(f'{where}: K {k} is not a calibrated camera matrix (uncalibrated cameras publish K = 0)')
    if len(d) > 5:
        raise RigError(f'{where}: plumb_bob takes 5 distortion coefficients, got {len(d)}')
    return camera_model(int(msg.width), int(msg.height), k[0], k[4], k[2], k[5], d, where)


def _numbers(cam: CameraModel) -> str:
    return (f'{cam.width}x{cam.height}, fx {cam.fx:g} fy {cam.fy:g} cx {cam.cx:g} cy {cam.cy:g}, '
            f'D {[round(x, 8) for x in cam.dist]}')


def disagreement(rig_cam: CameraModel, info_cam: CameraModel) -> str:
    """'' when the two agree within the tolerances, else what differs."""
    what = []
    if (rig_cam.width, rig_cam.height) != (info_cam.width, info_cam.height):
        what.append('image size')
    if max(abs(a - b) for a, b in zip((rig_cam.fx, rig_cam.fy, rig_cam.cx, rig_cam.cy),
                                      (info_cam.fx, info_cam.fy, info_cam.cx, info_cam.cy), strict=True)) > PX_TOL:
        what.append(f'K (beyond {PX_TOL:g} px)')
    if np.max(np.abs(rig_cam.dist_array - info_cam.dist_array)) > DIST_TOL:
        what.append(f'D (beyond {DIST_TOL:g})')
    return ', '.join(what)


@dataclass
class IntrinsicsFromInfo:
    """Fills a rig's missing intrinsics from the first CameraInfo of each camera and checks the given ones.

    ``on_info`` returns True when it changed :attr:`rig`; :attr:`errors` holds, per side, the one problem
    found (a disagreement with the rig file, or a CameraInfo that cannot be used), to log once and report."""

    rig: Rig
    seen: set[str] = field(default_factory=set)
    errors: dict[str, str] = field(default_factory=dict)
    source: dict[str, str] = field(default_factory=dict)      # side -> 'rig file' | 'camera_info'

    def __post_init__(self) -> None:
        self.source = {s: 'rig file' for s in SIDES if s not in self.rig.missing_intrinsics()}

    def ready(self, side: str) -> bool:
        return side not in self.rig.missing_intrinsics()

    def on_info(self, side: str, msg: Any) -> bool:
        if side in self.seen:
            return False
        self.seen.add(side)
        where = f'{side}/camera_info'
        try:
            cam = camera_from_info(msg, where)
        except ValueError as e:
            self.errors[side] = f'{e}' + ('' if self.ready(side) else f': no intrinsics for the {side} camera')
            return False
        if self.ready(side):
            diff = disagreement(self.rig.camera(side), cam)
            if diff:
                self.errors[side] = (f'{side} intrinsics: the rig file and {where} disagree on {diff}: rig file '
                                     f'{_numbers(self.rig.camera(side))}; camera_info {_numbers(cam)} (using the '
                                     'rig file)')
            return False
        size = self.rig.expected_size.get(side)
        if size is not None and size != (cam.width, cam.height):
            self.errors[side] = (f'{side} intrinsics: the rig file says {size[0]}x{size[1]} but {where} is '
                                 f'{cam.width}x{cam.height}: not used, no intrinsics for the {side} camera')
            return False
        self.rig = self.rig.with_camera(side, cam)
        self.source[side] = 'camera_info'
        return True
