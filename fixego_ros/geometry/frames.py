"""The TF tree of a rig as (parent, child, Pose) tuples: the nodes only convert and broadcast them.

Static: ``base_link`` -> ``rig`` (the mount, ``Rig.rig_in_base_link``), ``rig`` -> ``right_zero`` (identity:
the rig frame is the right camera's zero-pose frame) and ``rig`` -> ``left_zero`` (``R_L``, ``c_L``).
Moving: ``<side>_zero`` -> ``<side>_optical_frame``, the pan/tilt rotation at the joint readings (the
projection centre stays at the rotation centre, DESIGN.md §2). ``Pose`` maps child into parent coordinates,
as a TF transform from parent to child does.
"""

from __future__ import annotations

import math

import numpy as np

from fixego_ros.geometry.rig import SIDES, Rig, pan_tilt_rotation
from fixego_ros.geometry.rotation import Pose

RIG_FRAME = 'rig'     # the frame of /fixego/vergence and the flow observations


def zero_frame(side: str) -> str:
    return f'{side}_zero'


def optical_frame(side: str) -> str:
    """The image frame_id of DESIGN.md §3."""
    return f'{side}_optical_frame'


def static_transforms(rig: Rig, base_frame: str = 'base_link') -> list[tuple[str, str, Pose]]:
    """base_link -> rig -> each camera's zero-pose frame."""
    out = [(base_frame, RIG_FRAME, rig.rig_in_base_link)]
    out += [(RIG_FRAME, zero_frame(side), Pose(np.array(rig.zero_rotation(side), dtype=float),
                                               np.array(rig.center(side), dtype=float))) for side in SIDES]
    return out


def optical_transform(rig: Rig, side: str, pan_reading: float, tilt_reading: float) -> tuple[str, str, Pose]:
    """``<side>_zero`` -> ``<side>_optical_frame`` at the device's joint readings (rad; the rig file's
    pan_tilt calibration applied). ValueError for a non-finite reading."""
    if not (math.isfinite(pan_reading) and math.isfinite(tilt_reading)):
        raise ValueError(f'{side} joint readings must be finite, got pan {pan_reading}, tilt {tilt_reading}')
    pan, tilt = rig.calibration(side).kinematic(pan_reading, tilt_reading)
    return zero_frame(side), optical_frame(side), Pose(pan_tilt_rotation(pan, tilt), np.zeros(3))
