"""A fixed-lag window over GTSAM's ISAM2 that keeps the newest frame's variables at the root of the Bayes tree.

``gtsam.IncrementalFixedLagSmoother`` does the same bookkeeping but leaves the order inside the window to the
solver, so the newest pose can sit deep in the tree and its marginal covariance (wanted every frame for
``/fixego/odom``) costs a walk from the root: measured 35 ms of an 81 ms frame on the paper bag, 6 ms here.

The newest frame's keys are ordered last on the final relinearisation pass only. Constraining them on every
pass changes the elimination order of the earlier passes too; the sums come out in another order, and on the
unaided landmark scene (scale set only by the weak nominal-speed prior, a nearly flat direction) that rounding
grew into a path of 5.6 m instead of the prior's ~10.6 m. Constrained on the last pass, the window agrees with
``IncrementalFixedLagSmoother`` on that scene to within 8 % and gives the same paper-bag trajectory (to 1e-9 m).

Every variable is relinearised and re-eliminated at each update (``relinearizeThreshold`` 0). A threshold is a
decision that rounding flips: measured 13 cm RMS between OpenBLAS code paths on the paper bag with 0.01, 3e-10 m
with 0.

A numerical failure (GTSAM's "indeterminate linear system near variable v") is repaired in place rather than
handed up: the window is rebuilt from its own factors and linearisation point without that variable when it is
a landmark (a point whose views' robust kernels have given up on it), or with a weak prior on it otherwise (10x
firmer each time the same pose fails again within one update: on a live demo's frames a 1 rad / 10 m prior often
did not make the system determinate). Before, the smoother started a whole new graph, losing every landmark and
the measured scale; on a 30 Hz simulated loop that happened 35 times in 25 s and froze the trajectory for its
last 4 s.

A landmark that a Gauss-Newton pass leaves behind (or within ``MIN_DEPTH_M`` of) a camera that sees it is dropped
before the next pass: its projection factors are removed, its own prior keeps it determined until it is
marginalised at the next update, and the caller forgets it (``dropped``). A point with a short baseline has its depth
along a nearly flat direction, and one full step can throw it through the cameras' path (seen on a recorded demo:
eleven new landmarks 1.3-1.7 m ahead thrown behind the cameras in one pass). Behind a camera its projection factor
gives no Jacobian, the point is held by its 10 m prior alone against views of millimetres, and the next
factorisation fails as "indeterminate" (the recorded demo at 0.2 s frames: two restarts, 11.8 / 78.8 cm). The
decision is a threshold on a depth, not on a cost, so rounding does not flip it.
"""

from __future__ import annotations

import math
import re
from collections import Counter

import gtsam
import numpy as np

from fixego_ros.estimation.keys import camera_key, is_landmark, is_pose, landmark_key, pose_key

OLD, INSIDE, NEWEST = 0, 1, 2       # elimination groups: marginalised first, the window, the newest frame last
_CHR_POSE, _CHR_CAMERA, _CHR_LANDMARK = (np.uint64(gtsam.Symbol(k).chr())
                                         for k in (pose_key(0), camera_key(0, 'left'), landmark_key(0)))
_NO_VIEWS = np.zeros((0, 3), np.uint64)


def _key_list(keys) -> gtsam.KeyList:
    out = gtsam.KeyList()
    for k in keys:
        out.push_back(k)
    return out


def failed_variable(error: RuntimeError) -> int | None:
    """The key GTSAM names in an "indeterminate linear system" error (None for any other error)."""
    found = re.search(r'near variable\s+(\d+)', str(error))
    return int(found.group(1)) if found else None


def _at_its_point(factor: gtsam.LinearContainerFactor, theta: gtsam.Values) -> gtsam.LinearContainerFactor:
    """A marginal factor as ISAM2 keeps it (linear, about the frozen linearisation point of its variables: ISAM2
    never relinearises them) made to carry that point, so that a new ISAM2 may relinearise them. Copied as it is,
    the new ISAM2 moved their linearisation point and the factor kept pulling the same delta: the window lost its
    anchor and floated away (a recorded demo: every pose moved 1.1-1.3 m in one repair, docs/results.md "Stop 53")."""
    point, keys = gtsam.Values(), factor.keys()
    for k in keys:
        if is_landmark(k):
            point.insert(k, theta.atPoint3(k))
        else:
            point.insert(k, theta.atPose3(k))
    return gtsam.LinearContainerFactor(factor.factor(), point)


class FixedLagWindow:
    """Variables older than ``lag_s`` (by the stamp of their latest use) are marginalised out at each update."""

    MAX_REPAIRS = 5                     # per update; then the failure is raised (and the smoother restarts)
    MIN_DEPTH_M = 0.3                   # a landmark this close to (or behind) a camera that sees it is dropped
    MAX_DROP_PASSES = 2                 # extra passes per update after the last one dropped landmarks
    REPAIR_SIGMAS = (1.0, 10.0)         # the weak prior on a pose or camera it failed near (rad, m)

    def __init__(self, lag_s: float) -> None:
        self.lag_s = lag_s
        self._isam = self._new_isam()
        self._stamps: dict[int, float] = {}
        self.repairs: list[str] = []    # what each repair did (the caller reports them)
        self.dropped: list[int] = []    # landmarks dropped behind a camera (the caller forgets them)
        self._views = _NO_VIEWS         # projection factors: rows (index in ISAM2, camera key, landmark key)
        self._pending: list[int] = []                   # projection factors to remove at the next update
        self._theta: gtsam.Values | None = None         # the estimate, once computed after the last change

    @staticmethod
    def _new_isam() -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.0)
        params.relinearizeSkip = 1
        return gtsam.ISAM2(params)

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
               newest: tuple[int, ...] = (), iterations: int = 0) -> None:
        """Add factors and new variables (``stamps`` gives each new or re-used key its time), marginalise what has
        left the window, then relinearise ``iterations`` more times. A numerical failure is repaired (module
        docstring); RuntimeError when that does not work."""
        try:
            self._update(graph, values, stamps, newest, iterations)
        except RuntimeError as error:
            self._repair(error, newest, iterations)

    def _repair(self, error: RuntimeError, newest: tuple[int, ...], iterations: int) -> None:
        """Rebuild the window from the failed ISAM2's factors and linearisation point (they hold this update's
        additions), without or anchoring the variable it failed near; repeat while it fails near another one."""
        anchored: Counter[int] = Counter()     # poses anchored in this update, and how often
        for _ in range(self.MAX_REPAIRS):
            key = failed_variable(error)
            if key is None or not (is_landmark(key) or is_pose(key)):
                raise error
            name = gtsam.Symbol(key).string()
            factors, theta = self._isam.getFactorsUnsafe(), self._isam.getLinearizationPoint()
            pending = set(self._pending)
            kept = [f for f in (factors.at(i) for i in range(factors.size()) if i not in pending) if f is not None]
            marginals = [f for f in kept if isinstance(f, gtsam.LinearContainerFactor)]
            drop = is_landmark(key) and not any(key in list(m.keys()) for m in marginals)
            graph = gtsam.NonlinearFactorGraph()
            for factor in kept:
                if not (drop and key in list(factor.keys())):
                    graph.add(_at_its_point(factor, theta) if isinstance(factor, gtsam.LinearContainerFactor)
                              else factor)
            if drop:
                theta.erase(key)
                self._stamps.pop(key, None)
                self.repairs.append(f'dropped {name}')
            else:
                rotation, position = self.REPAIR_SIGMAS       # 10x firmer each time the same variable fails again
                scale = 10.0 ** anchored[key]
                anchored[key] += 1
                if is_landmark(key):
                    prior = gtsam.PriorFactorPoint3(key, theta.atPoint3(key),
                                                    gtsam.noiseModel.Isotropic.Sigma(3, position / scale))
                else:
                    prior = gtsam.PriorFactorPose3(key, theta.atPose3(key), gtsam.noiseModel.Diagonal.Sigmas(
                        np.array([rotation] * 3 + [position] * 3) / scale))
                graph.add(prior)
                self.repairs.append(f'anchored {name}')
            stamps = {k: s for k, s in self._stamps.items() if theta.exists(k)}
            self._stamps, self._views, self._pending = {}, _NO_VIEWS, []
            self._isam = self._new_isam()
            try:
                self._update(graph, theta, stamps, newest, iterations)
                return
            except RuntimeError as failure:
                error = failure
        raise error

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
                newest: tuple[int, ...], iterations: int) -> None:
        keys = _key_list(self._stamps)  # re-eliminate everything already in the tree, so the groups hold
        self._stamps.update(stamps)
        now = max(self._stamps.values(), default=0.0)
        old = [k for k, s in self._stamps.items() if s < now - self.lag_s]
        gone = set(old)
        remove, self._pending = self._pending, []
        passes = 1 + iterations
        step = 0
        while step < passes:
            last = step == passes - 1
            group = {k: OLD if k in gone and step == 0 else NEWEST if k in newest and last else INSIDE
                     for k in self._stamps}
            rank = {g: r for r, g in enumerate(sorted(set(group.values())))}     # CCOLAMD wants groups 0..n-1
            groups = gtsam.KeyGroupMap()
            for k, g in group.items():
                groups.insert2(k, rank[g])
            new = graph if step == 0 else gtsam.NonlinearFactorGraph()
            self._theta = None
            result = self._isam.update(new, values if step == 0 else gtsam.Values(), remove, groups, None, keys, True)
            if remove:
                self._views = self._views[~np.isin(self._views[:, 0], np.array(remove, np.uint64))]
            if step == 0:
                self._record(graph, result.getNewFactorsIndices())
                if old:
                    self._isam.marginalizeLeaves(_key_list(old))
                    for k in old:
                        del self._stamps[k]
                    keys = _key_list(self._stamps)
            remove = self._drop_behind()
            if last and remove:
                if passes < 1 + iterations + self.MAX_DROP_PASSES:
                    passes += 1
                else:
                    self._pending = remove      # removed by the next update's first pass
            step += 1

    def _record(self, graph: gtsam.NonlinearFactorGraph, indices) -> None:
        """Remember which new factors are projections (camera, landmark), by their index in ISAM2."""
        rows = [(indices[j], *graph.at(j).keys()) for j in range(graph.size())
                if isinstance(graph.at(j), gtsam.GenericProjectionFactorCal3_S2)]
        if rows:
            self._views = np.concatenate([self._views, np.array(rows, np.uint64)])

    def _drop_behind(self) -> list[int]:
        """Indices of the projection factors of every landmark now within ``MIN_DEPTH_M`` of, or behind, a camera
        that sees it (module docstring). Those landmarks leave the window at the next update."""
        if not len(self._views):
            return []
        theta = self._theta = self._isam.calculateEstimate()     # all at once: a call per key cost ~40 ms a frame
        keys = np.asarray(theta.keys(), np.uint64)  # sorted
        found = [keys[np.minimum(np.searchsorted(keys, self._views[:, c]), len(keys) - 1)] == self._views[:, c]
                 for c in (1, 2)]
        self._views = self._views[found[0] & found[1]]     # the rest were marginalised with their variables
        kind = keys >> np.uint64(56)                # the symbol's character
        pose_keys = keys[(kind == _CHR_POSE) | (kind == _CHR_CAMERA)]
        point_keys = keys[kind == _CHR_LANDMARK]
        poses, points = gtsam.utilities.extractPose3(theta), gtsam.utilities.extractPoint3(theta)
        if len(poses) != len(pose_keys) or len(points) != len(point_keys):
            return []                               # a variable of another kind: the rows would not match the keys
        camera = poses[np.searchsorted(pose_keys, self._views[:, 1])]     # rows: R row-major (9), t (3)
        point = points[np.searchsorted(point_keys, self._views[:, 2])]
        depth = np.einsum('ij,ij->i', camera[:, [2, 5, 8]], point - camera[:, 9:])
        bad = ~(depth >= self.MIN_DEPTH_M)
        if not bad.any():
            return []
        dropped = np.unique(self._views[bad, 2])
        for m in dropped:
            self._stamps[int(m)] = -math.inf    # held by its own prior until then
        self.dropped.extend(int(m) for m in dropped)
        return [int(i) for i in self._views[np.isin(self._views[:, 2], dropped), 0]]

    def estimate(self) -> gtsam.Values:
        """The current estimate (the behind-camera check's, when nothing has changed since)."""
        if self._theta is None:
            self._theta = self._isam.calculateEstimate()
        return self._theta

    def marginal_covariance(self, key: int) -> np.ndarray:
        """Marginal covariance in the variable's tangent space (cheap for the newest frame's keys)."""
        return np.asarray(self._isam.marginalCovariance(key), float)
