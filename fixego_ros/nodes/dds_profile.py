"""The Fast DDS profile of the nodes that publish images (``config/fastdds_images.xml``).

Fast DDS sends samples to processes on the same host through one shared-memory segment per participant,
512 KB by default: one 640x480 image. Publishing a stereo pair then recycles the first image's buffer while
slower readers still need it, and they lose that image without any error (best-effort sensor QoS). The
package's profile gives image publishers an 8 MB segment. It is applied through the environment before
``rclpy.init`` and only when the user has named no profile file and the middleware is Fast DDS.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path

from fixego_ros.geometry.rig import default_rig_path

PROFILE_ENV = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')   # Fast DDS 2.x, 3.x
PROFILE_NAME = 'fastdds_images.xml'


def profile_path() -> Path:
    """``config/fastdds_images.xml`` of the source tree or of the installed package (share/)."""
    return default_rig_path().with_name(PROFILE_NAME)


def use_image_profile(environ: MutableMapping[str, str] | None = None) -> str:
    """Point Fast DDS at the package's profile unless the user chose one or another middleware. Returns one
    line for the node's start-up log saying which profile is in use and why."""
    env = os.environ if environ is None else environ
    rmw = env.get('RMW_IMPLEMENTATION', '')
    if rmw and 'fastrtps' not in rmw and 'fastdds' not in rmw:
        return f'RMW_IMPLEMENTATION is {rmw}: its own transport settings apply to the images'
    for name in PROFILE_ENV:
        if env.get(name):
            return f'Fast DDS profile from {name}: {env[name]} (give image publishers a shared-memory segment of ' \
                   f'several images, see {PROFILE_NAME})'
    path = profile_path()
    if not path.is_file():
        return f'{path} missing: Fast DDS default transports (a 512 KB shared-memory segment loses stereo images)'
    for name in PROFILE_ENV:
        env[name] = str(path)
    return f'Fast DDS profile {path} (8 MB shared-memory segment for images)'
