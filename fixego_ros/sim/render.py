"""Render a camera's view of the :class:`~fixego_ros.sim.world.World` from the true rig pose and pan/tilt.

Each visible rectangle is drawn with one homography (``cv2.warpPerspective`` of its texture into the
bounding box of its projection) and a polygon mask of the rectangle clipped to the view frustum, so
the pinhole geometry is exact to interpolation accuracy. Occlusion: the room is convex and seen from
inside, so its surfaces never overlap each other; they are drawn first, then the boxes far to near
(painter's order by distance to the box), each with back faces culled (boxes are convex).

Kinematics follow DESIGN.md §2 through :class:`~fixego_ros.geometry.rig.Rig`: a world point ``X``
seen by camera ``side`` with the rig pose ``P_wr`` (rig -> world) and joint readings ``(p, t)`` has
optical-frame coordinates ``C.T @ (P_wr.inverse().apply(X) - rig.center(side))`` with
``C = rig.cam_to_rig(side, p, t)``. Lens distortion, if the rig file has any, is applied with a
precomputed remap of an ideal (pinhole) canvas.
"""

from __future__ import annotations

import cv2
import numpy as np

from fixego_ros.geometry.rig import CameraModel, Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.world import Plane, World

ENCODINGS = ('mono8', 'rgb8')
NOISE_MAX = 255.0   # grey levels: the largest sensor noise sigma (a larger one only saturates; NaN/inf corrupt)


def world_to_camera(rig: Rig, side: str, rig_pose: Pose, pan_reading: float,
                    tilt_reading: float) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` with optical-frame coordinates ``A @ X + b`` of a world point ``X``."""
    C = rig.cam_to_rig(side, pan_reading, tilt_reading)
    A = C.T @ rig_pose.R.T
    b = -C.T @ (rig_pose.R.T @ rig_pose.t + rig.center(side))
    return A, b


def camera_center_world(rig: Rig, side: str, rig_pose: Pose) -> np.ndarray:
    """Projection centre of ``side`` in the world frame."""
    return rig_pose.apply(rig.center(side))


def project_points(rig: Rig, side: str, rig_pose: Pose, pan_reading: float, tilt_reading: float,
                   X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) (with the camera's distortion) and depths (N,) of world points (N, 3)."""
    A, b = world_to_camera(rig, side, rig_pose, pan_reading, tilt_reading)
    d = np.asarray(X, dtype=float).reshape(-1, 3) @ A.T + b
    return rig.camera(side).rays_to_pixels(d), d[:, 2]


def _clip_polygon(poly: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: keep the part of a convex 3D polygon with ``m . p + k >= 0`` for each (m, k). A polygon
    wholly outside one plane is empty, one wholly inside every plane is itself: both decided from one product, as most
    of a room's rectangles are one or the other in each frame (the loop below cost ~20 % of a render)."""
    s_all = poly @ planes[:, :3].T + planes[:, 3]
    if (s_all < 0).all(axis=0).any():
        return poly[:0]
    if (s_all >= 0).all():
        return poly
    for plane in planes:
        if len(poly) == 0:
            break
        m, k = plane[:3], plane[3]
        s = poly @ m + k
        out = []
        n = len(poly)
        for i in range(n):
            j = (i + 1) % n
            if s[i] >= 0:
                out.append(poly[i])
            if (s[i] >= 0) != (s[j] >= 0):
                a = s[i] / (s[i] - s[j])
                out.append(poly[i] + a * (poly[j] - poly[i]))
        poly = np.array(out).reshape(-1, 3)
    return poly


class _Canvas:
    """Ideal pinhole image a camera is rendered into (larger than the image when undistorting)."""

    def __init__(self, cam: CameraModel, near: float) -> None:
        self.cam = cam
        self.remap: tuple[np.ndarray, np.ndarray] | None = None
        ox = oy = 0.0
        w, h = cam.width, cam.height
        if cam.has_distortion:
            # ideal coordinates of every distorted output pixel; the canvas must cover all of them
            uu, vv = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
            uv = np.column_stack([uu.ravel(), vv.ravel()])
            rays = cam.pixels_to_rays(uv)
            ideal = cam.rays_to_pixels(rays, distort=False)
            lo = np.floor(ideal.min(axis=0)) - 2
            hi = np.ceil(ideal.max(axis=0)) + 2
            ox, oy = -lo[0], -lo[1]
            w, h = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
            mx = (ideal[:, 0] + ox).reshape(cam.height, cam.width).astype(np.float32)
            my = (ideal[:, 1] + oy).reshape(cam.height, cam.width).astype(np.float32)
            self.remap = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        self.width, self.height = w, h
        self.K = np.array([[cam.fx, 0.0, cam.cx + ox], [0.0, cam.fy, cam.cy + oy], [0.0, 0.0, 1.0]])
        fx, fy, cx, cy, m = cam.fx, cam.fy, cam.cx + ox, cam.cy + oy, 2.0
        # frustum half-spaces (m . p + k >= 0) in optical coordinates, a 2 px margin around the canvas
        self.frustum = np.array([
            [0.0, 0.0, 1.0, -near],
            [fx, 0.0, cx + m, 0.0],
            [-fx, 0.0, (w - 1 + m) - cx, 0.0],
            [0.0, fy, cy + m, 0.0],
            [0.0, -fy, (h - 1 + m) - cy, 0.0],
        ])


class Renderer:
    """Renders grey (mono8) or colour (rgb8) images of a world for both cameras of a rig, with noise."""

    def __init__(self, world: World, rig: Rig, encoding: str = 'mono8', noise_sigma: float = 2.0,
                 seed: int = 0, near: float = 0.05, mipmap: bool = True, warm: bool = True) -> None:
        if encoding not in ENCODINGS:
            raise ValueError(f'encoding must be one of {ENCODINGS}, got {encoding!r}')
        if not (np.isfinite(noise_sigma) and 0.0 <= noise_sigma <= NOISE_MAX):
            raise ValueError(f'noise sigma must be a finite number in [0, {NOISE_MAX:g}] grey levels, got '
                             f'{noise_sigma!r}')
        self.world, self.rig, self.encoding = world, rig, encoding
        self.noise_sigma = float(noise_sigma)
        self.mipmap = mipmap
        self.rgb = encoding == 'rgb8'
        self._canvas = {side: _Canvas(rig.camera(side), near) for side in ('right', 'left')}
        self._rng = np.random.default_rng([int(seed), 0x0D15E])
        self._noise_bank: dict[str, np.ndarray] = {}
        self._groups = self._box_groups()
        if warm:
            self.warm()

    def warm(self) -> None:
        """Build every texture level now, so no frame pays for it later (~1 s for rgb8, once per world)."""
        for p in self.world.planes:
            for level in range(5 if self.mipmap else 1):
                p.texture_level(level, self.rgb)

    def _box_groups(self) -> dict[int, tuple[np.ndarray, np.ndarray, list[Plane]]]:
        groups: dict[int, list[Plane]] = {}
        for p in self.world.planes:
            if p.group >= 0:
                groups.setdefault(p.group, []).append(p)
        out = {}
        for g, planes in groups.items():
            pts = np.concatenate([p.corners for p in planes])
            out[g] = (pts.min(axis=0), pts.max(axis=0), planes)
        return out

    def _noise(self, side: str, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """A window of a precomputed Gaussian noise bank (drawing 300k normals per frame costs ~4 ms)."""
        margin = 32
        bank = self._noise_bank.get(side)
        if bank is None or bank.shape[1:3] != (shape[0] + margin, shape[1] + margin):
            bank_rng = np.random.default_rng([int(self._rng.integers(2**31)), len(side)])
            full = (8, shape[0] + margin, shape[1] + margin, *shape[2:])
            bank = np.round(bank_rng.standard_normal(full, dtype=np.float32) * self.noise_sigma).astype(np.int16)
            self._noise_bank[side] = bank
        i, dy, dx = rng.integers(0, 8), rng.integers(0, margin), rng.integers(0, margin)
        return bank[i, dy:dy + shape[0], dx:dx + shape[1]]

    def render(self, side: str, rig_pose: Pose, pan_reading: float, tilt_reading: float,
               noise: bool = True, rng: np.random.Generator | None = None) -> np.ndarray:
        """Image of ``side`` (uint8, (H, W) or (H, W, 3)); ``rng`` (default: the renderer's) drives noise."""
        canvas = self._canvas[side]
        A, b = world_to_camera(self.rig, side, rig_pose, pan_reading, tilt_reading)
        eye = camera_center_world(self.rig, side, rig_pose)
        shape = (canvas.height, canvas.width, 3) if self.rgb else (canvas.height, canvas.width)
        img = np.zeros(shape, np.uint8)
        room = [p for p in self.world.planes if p.group < 0]
        for p in room:
            self._draw_plane(img, p, A, b, eye, canvas)
        order = sorted(self._groups.values(), key=lambda g: -np.linalg.norm(np.clip(eye, g[0], g[1]) - eye))
        for _, _, planes in order:
            for p in planes:
                self._draw_plane(img, p, A, b, eye, canvas)
        if canvas.remap is not None:
            img = cv2.remap(img, canvas.remap[0], canvas.remap[1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
        if noise and self.noise_sigma > 0:
            n = self._noise(side, img.shape, self._rng if rng is None else rng)
            img = cv2.add(img, n, dtype=cv2.CV_8U)
        return img

    def _draw_plane(self, img: np.ndarray, p: Plane, A: np.ndarray, b: np.ndarray, eye: np.ndarray,
                    canvas: _Canvas) -> None:
        if float(np.dot(p.normal, eye - p.origin)) <= 1e-9:
            return  # back face (or edge-on)
        poly = _clip_polygon(p.corners @ A.T + b, canvas.frustum)
        if len(poly) < 3:
            return
        K = canvas.K
        pix = (poly @ K.T)
        pix = pix[:, :2] / pix[:, 2:3]
        x0 = max(int(np.floor(pix[:, 0].min())), 0)
        y0 = max(int(np.floor(pix[:, 1].min())), 0)
        x1 = min(int(np.ceil(pix[:, 0].max())) + 1, canvas.width)
        y1 = min(int(np.ceil(pix[:, 1].max())) + 1, canvas.height)
        if x1 <= x0 or y1 <= y0:
            return
        level = 0
        if self.mipmap:
            # texels per pixel at the polygon's centroid, including foreshortening
            c = poly.mean(axis=0)
            cosang = abs(float(np.dot(A @ p.normal, c / np.linalg.norm(c))))
            ratio = c[2] / (K[0, 0] * p.texel * max(cosang, 0.25))
            level = int(np.clip(np.floor(np.log2(max(ratio, 1.0) * 0.9)), 0, 4)) if ratio >= 2.0 else 0
        tex = p.texture_level(level, self.rgb)
        s = p.texel * (1 << level)
        M = np.column_stack([A @ (p.u * s), A @ (p.v * s), A @ p.origin + b])
        H = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ K @ M
        roi = img[y0:y1, x0:x1]
        warped = cv2.warpPerspective(tex, H, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        shift = 4
        pts = np.round((pix - [x0, y0]) * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_8, shift)
        cv2.copyTo(warped, mask, roi)
