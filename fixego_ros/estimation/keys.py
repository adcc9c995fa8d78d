"""Typed keys of the factor graph (GTSAM symbols), one helper per variable kind.

``x<i>`` is the rig pose at frame ``i`` (rig frame at frame 0 as the world); ``c<2i+side>`` is one camera's
optical frame at frame ``i`` (its pan/tilt makes it a variable of its own, tied to the rig by
:class:`~fixego_ros.estimation.factors.CameraMount`); ``l<n>`` is a landmark (a tracked point or a fixation point);
``k<g>`` is the scale of the speed source (its wheel radius error; a double), ``g`` counting its variables.
"""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import gtsam
from gtsam.symbol_shorthand import C, K, L, X

from fixego_ros.geometry.rig import SIDES


class LandmarkKind(IntEnum):
    FIXATION = 0      # a camera's fixation point (id from its fixation topic)
    TRACK = 1         # a persistent flow track (id from the front end, never reused within a camera)


class LandmarkId(NamedTuple):
    """What the front end calls a scene point: its kind, the camera that sees it and that camera's id."""

    kind: LandmarkKind
    side: str
    ident: int


def pose_key(frame: int) -> int:
    return X(frame)


def camera_key(frame: int, side: str) -> int:
    return C(2 * frame + SIDES.index(side))


def landmark_key(index: int) -> int:
    return L(index)


def speed_scale_key(graph: int) -> int:
    return K(graph)


def is_landmark(key: int) -> bool:
    return gtsam.Symbol(key).chr() == gtsam.Symbol(L(0)).chr()


def is_pose(key: int) -> bool:
    """A rig pose or a camera pose (both Pose3)."""
    return gtsam.Symbol(key).chr() in (gtsam.Symbol(X(0)).chr(), gtsam.Symbol(C(0)).chr())
