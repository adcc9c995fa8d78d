"""A fixed-lag window: Gauss-Newton over the window's factors, one batch elimination per pass, with the variables
that leave the window marginalised into linear factors about the point where they left.

Each pass linearises every factor and eliminates the whole window (COLAMD; the newest frame's keys ordered last on
the final pass, so their marginal covariance, wanted for ``/fixego/odom``, is read off the root clique). Until stop
64 the window was a GTSAM ``ISAM2`` told to relinearise and re-eliminate everything at each update
(``relinearizeThreshold`` 0: a threshold is a decision that rounding flips, measured 13 cm RMS between OpenBLAS code
paths on the paper bag with 0.01). That is the same arithmetic with the Bayes tree's bookkeeping on top: on a 30 Hz
loop's window (3750 factors, 330 variables) one ISAM2 pass took 31 ms, one pass here 21 ms (linearise 5, order 1,
eliminate 13, solve 1). The trajectories are the same to the 0.1 mm on the shipped and simulated bags.

Variables older than ``lag_s`` (by the stamp of their latest use) leave after the first pass: the factors on them
are linearised at that pass's point, the old variables eliminated from those alone, and what remains on the
variables still in the window is kept as a ``gtsam.LinearContainerFactor`` that carries its linearisation point.
The variables such a marginal holds are linearised at that point from then on, in every factor, as ISAM2 does (its
"fixed variables"; first-estimate Jacobians): relinearised at the estimate instead, the marginal's information met
Jacobians from another point and claimed what the window cannot know, its scale most of all. Measured at stop 64:
the 30 Hz loop bags' paths 3-6 % shorter, mean error 2.4 -> 6.7 cm, the rested loop 3.0 -> 13.6 cm, `bags/paper`
1.9 -> 4.4.

A numerical failure (GTSAM's "indeterminate linear system near variable v") is repaired in place rather than
handed up: a landmark that no marginal holds is dropped with its factors (a point whose views' robust kernels have
given up on it), another variable gets a weak prior where it is (10x firmer each time it fails again within one
update: on a live demo's frames a 1 rad / 10 m prior often did not make the system determinate). Before stop 53
the smoother started a whole new graph, losing every landmark and the measured scale; on a 30 Hz simulated loop
that happened 35 times in 25 s and froze the trajectory for its last 4 s.

A landmark that a pass leaves behind (or within ``MIN_DEPTH_M`` of) a camera that sees it loses its projection
factors before the next pass: its own prior keeps it determined until it is marginalised at the next update, and
the caller forgets it (``dropped``). A point with a short baseline has its depth along a nearly flat direction, and
one full step can throw it through the cameras' path (seen on a recorded demo: eleven new landmarks 1.3-1.7 m ahead
thrown behind the cameras in one pass). Behind a camera its projection factor gives no Jacobian, the point is held
by its 10 m prior alone against views of millimetres, and the next factorisation fails as "indeterminate" (the
recorded demo at 0.2 s frames: two restarts, 11.8 / 78.8 cm). The decision is a threshold on a depth, not on a
cost, so rounding does not flip it.
"""

from __future__ import annotations

import math
import re
from collections import Counter

import gtsam
import numpy as np

from fixego_ros.estimation.keys import camera_key, is_landmark, is_pose, landmark_key, pose_key
from fixego_ros.estimation.stage_times import Stage, StageTimes

_CHR_POSE, _CHR_CAMERA, _CHR_LANDMARK = (np.uint64(gtsam.Symbol(k).chr())
                                         for k in (pose_key(0), camera_key(0, 'left'), landmark_key(0)))
_NO_VIEWS = np.zeros((0, 3), np.uint64)


def failed_variable(error: RuntimeError) -> int | None:
    """The key GTSAM names in an "indeterminate linear system" error (None for any other error)."""
    found = re.search(r'near variable\s+(\d+)', str(error))
    return int(found.group(1)) if found else None


def _split_keys(values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The keys (sorted, uint64), and among them those of poses and cameras and those of landmarks (by the symbol's
    character)."""
    keys = np.asarray(values.keys(), np.uint64)
    kind = keys >> np.uint64(56)
    return keys, keys[(kind == _CHR_POSE) | (kind == _CHR_CAMERA)], keys[kind == _CHR_LANDMARK]


def _value(values: gtsam.Values, key: int) -> gtsam.Pose3 | np.ndarray | float:
    """One variable's value, typed (the window holds poses, points and doubles)."""
    if is_landmark(key):
        return values.atPoint3(key)
    if is_pose(key):
        return values.atPose3(key)
    for get in (values.atPose3, values.atPoint3, values.atDouble):
        try:
            return get(key)
        except RuntimeError:
            continue
    raise RuntimeError(f'no value of a known type at {gtsam.Symbol(key).string()}')   # the smoother restarts


class FixedLagWindow:
    """Variables older than ``lag_s`` (by the stamp of their latest use) are marginalised out at each update."""

    MAX_REPAIRS = 5                     # per update; then the failure is raised (and the smoother restarts)
    MIN_DEPTH_M = 0.3                   # a landmark this close to (or behind) a camera that sees it is dropped
    MAX_DROP_PASSES = 2                 # extra passes per update after the last one dropped landmarks
    REPAIR_SIGMAS = (1.0, 10.0)         # the weak prior on a pose or camera it failed near (rad, m)
    STEP_TOLERANCE = (1e-3, 2e-3)       # a pass that moves no pose by more (rad, m) ends the update's passes

    def __init__(self, lag_s: float, times: StageTimes | None = None) -> None:
        self.lag_s = lag_s
        self.times = times or StageTimes()     # where each pass's time goes (the caller clears it)
        self.repairs: list[str] = []    # what each repair did (the caller reports them)
        self.dropped: list[int] = []    # landmarks dropped behind a camera (the caller forgets them)
        self._graph = gtsam.NonlinearFactorGraph()      # a removed factor leaves an empty slot until compaction
        self._keys: list[tuple[int, ...] | None] = []   # each slot's keys (None: empty)
        self._by_key: dict[int, set[int]] = {}          # the slots of the factors on each variable
        self._theta = gtsam.Values()    # the estimate
        self._lin = gtsam.Values()      # the last pass's linearisation point
        self._fixed: set[int] = set()   # variables a marginal holds: linearised at their point when it was made
        self._stamps: dict[int, float] = {}
        self._views = _NO_VIEWS         # projection factors: rows (slot, camera key, landmark key)
        self._repaired = 0              # repairs in this update
        self._tree: gtsam.GaussianBayesTree | None = None   # the last pass's elimination (newest keys last)
        self._tree_dims: dict[int, int] = {}    # its variables' sizes (some may have left the window since)
        self._root: tuple[tuple[int, ...], np.ndarray] | None = None    # its root's keys and covariance, once asked
        self.passes: Counter[int] = Counter()   # how many updates took how many Gauss-Newton passes

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
               newest: tuple[int, ...] = (), iterations: int = 0) -> None:
        """Add factors and new variables (``stamps`` gives each new or re-used key its time), relinearise
        ``1 + iterations`` times and marginalise what has left the window after the first pass. A numerical failure
        is repaired (module docstring); RuntimeError when that does not work."""
        self._theta.insert(values)
        self._stamps.update(stamps)
        self._add([graph.at(i) for i in range(graph.size())])
        now = max(self._stamps.values(), default=0.0)
        old = [k for k, s in self._stamps.items() if s < now - self.lag_s]
        anchored: Counter[int] = Counter()     # variables anchored in this update, and how often
        self._repaired = 0
        passes, step = 1 + iterations, 0
        while step < passes:
            last = step == passes - 1
            moved = self._step(newest, anchored)
            if step == 0 and old:
                with self.times(Stage.MARGINALISE):
                    self._marginalise(old)
            dropped = self._drop_behind()
            if dropped:
                self._remove(dropped)
                if last and passes < 1 + iterations + self.MAX_DROP_PASSES:
                    passes += 1
            elif not moved:
                break
            step += 1
        self.passes[min(step + 1, passes)] += 1     # passes made (step is the last one's index after a break)
        if 2 * len(self._keys) > 3 * (len(self._keys) - self._keys.count(None)) + 64:
            self._compact()

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """The window's nonlinear factors (a removed one leaves None in its slot)."""
        return self._graph

    def estimate(self) -> gtsam.Values:
        """The current estimate."""
        return self._theta

    def marginal_covariance(self, key: int) -> np.ndarray:
        """Marginal covariance in the variable's tangent space, about the last pass's linearisation point (cheap for
        the newest frame's keys: they sit in the root clique, whose covariance is the inverse of its R'R)."""
        if self._tree is None:
            raise RuntimeError('no elimination yet')
        if self._root is None:
            root = self._tree.roots()[0].conditional()
            R = np.asarray(root.R(), float)
            Rinv = np.linalg.solve(R, np.eye(len(R)))
            self._root = (tuple(root.keys()), Rinv @ Rinv.T)
        keys, cov = self._root
        if key not in keys:
            return np.asarray(self._tree.marginalCovariance(key), float)
        dims = self._tree_dims      # not the estimate's: with no extra pass the old variables left after this one
        start = sum(dims[k] for k in keys[:keys.index(key)])
        end = start + dims[key]
        return cov[start:end, start:end].copy()

    # --- the factors

    def _add(self, factors: list[gtsam.NonlinearFactor]) -> None:
        rows = []
        for factor in factors:
            slot = len(self._keys)
            keys = tuple(factor.keys())
            self._graph.add(factor)
            self._keys.append(keys)
            for k in keys:
                self._by_key.setdefault(k, set()).add(slot)
            if isinstance(factor, gtsam.GenericProjectionFactorCal3_S2):
                rows.append((slot, *keys))
        if rows:
            self._views = np.concatenate([self._views, np.array(rows, np.uint64)])

    def _remove(self, slots: list[int]) -> None:
        for slot in slots:
            keys = self._keys[slot]
            if keys is None:
                continue
            self._graph.remove(slot)
            self._keys[slot] = None
            for k in keys:
                self._by_key[k].discard(slot)
        if len(self._views):
            self._views = self._views[~np.isin(self._views[:, 0], np.array(slots, np.uint64))]

    def _compact(self) -> None:
        """Rebuild the graph without its empty slots (they cost nothing to eliminate, but memory and a walk)."""
        kept = [s for s, keys in enumerate(self._keys) if keys is not None]
        factors = [self._graph.at(s) for s in kept]
        self._graph, self._keys, self._by_key, self._views = gtsam.NonlinearFactorGraph(), [], {}, _NO_VIEWS
        self._add(factors)

    def _forget(self, key: int) -> None:
        """Erase a variable (one a repair dropped may still be listed among this update's old ones)."""
        if self._theta.exists(key):
            self._theta.erase(key)
        if self._lin.exists(key):
            self._lin.erase(key)
        self._fixed.discard(key)
        self._stamps.pop(key, None)
        self._by_key.pop(key, None)

    # --- the passes

    def _step(self, newest: tuple[int, ...], anchored: Counter[int]) -> bool:
        """One Gauss-Newton step over the whole window, repairing a numerical failure (module docstring). Whether
        it moved a pose by more than ``STEP_TOLERANCE`` (else another pass would change little)."""
        while True:
            lin = gtsam.Values(self._theta)
            for k in self._fixed:
                lin.update(k, _value(self._lin, k))
            with self.times(Stage.LINEARISE):
                linear = self._graph.linearize(lin)
            present = [k for k in newest if self._theta.exists(k)]
            with self.times(Stage.ORDER):
                order = (gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(linear, gtsam.KeyVector(present))
                         if present else gtsam.Ordering.ColamdGaussianFactorGraph(linear))
            try:
                with self.times(Stage.ELIMINATE):
                    tree = linear.eliminateMultifrontal(order)
                break
            except RuntimeError as error:
                if self._repaired >= self.MAX_REPAIRS:
                    raise
                self._repaired += 1
                self._repair(error, anchored)
        self._tree, self._tree_dims, self._root, self._lin = tree, lin.dims(), None, lin
        with self.times(Stage.SOLVE):
            delta = tree.optimize()
            self._theta = lin.retract(delta)
        rotation, translation = self.STEP_TOLERANCE
        for k in _split_keys(lin)[1]:
            d = delta.at(int(k))
            if np.abs(d[:3]).max() > rotation or np.abs(d[3:]).max() > translation:
                return True
        return False

    def _repair(self, error: RuntimeError, anchored: Counter[int]) -> None:
        key = failed_variable(error)
        if key is None or not (is_landmark(key) or is_pose(key)) or not self._theta.exists(key):
            raise error
        name = gtsam.Symbol(key).string()
        slots = sorted(self._by_key.get(key, ()))
        held = any(isinstance(self._graph.at(s), gtsam.LinearContainerFactor) for s in slots)
        if is_landmark(key) and not held:
            self._remove(slots)
            self._forget(key)
            self.repairs.append(f'dropped {name}')
            return
        rotation, position = self.REPAIR_SIGMAS       # 10x firmer each time the same variable fails again
        scale = 10.0 ** anchored[key]
        anchored[key] += 1
        if is_landmark(key):
            prior = gtsam.PriorFactorPoint3(key, self._theta.atPoint3(key),
                                            gtsam.noiseModel.Isotropic.Sigma(3, position / scale))
        else:
            prior = gtsam.PriorFactorPose3(key, self._theta.atPose3(key), gtsam.noiseModel.Diagonal.Sigmas(
                np.array([rotation] * 3 + [position] * 3) / scale))
        self._add([prior])
        self.repairs.append(f'anchored {name}')

    def _marginalise(self, old: list[int]) -> None:
        """Eliminate the old variables from the factors on them, at the estimate; keep what remains on the others
        as linear factors about that point (module docstring)."""
        slots = sorted(set().union(*(self._by_key.get(k, set()) for k in old)))
        involved = [k for k in old if self._by_key.get(k)]
        marginals = []
        if involved:
            factors = gtsam.NonlinearFactorGraph()
            for s in slots:
                factors.add(self._graph.at(s))
            try:
                _, rest = factors.linearize(self._lin).eliminatePartialMultifrontal(gtsam.Ordering(involved))
                marginals = [rest.at(i) for i in range(rest.size())]
            except RuntimeError as error:      # not seen: the whole window was just eliminated without failure
                self.repairs.append(f'marginalised without their information: {str(error).strip()[:80]}')
        self._remove(slots)
        kept = []
        for factor in marginals:
            keys = [] if factor is None else list(factor.keys())
            if keys:
                point = gtsam.Values()
                for k in keys:
                    point.insert(k, _value(self._lin, k))
                kept.append(gtsam.LinearContainerFactor(factor, point))
                self._fixed.update(keys)
        for k in old:
            self._forget(k)
        self._add(kept)

    def _drop_behind(self) -> list[int]:
        """Slots of the projection factors of every landmark now within ``MIN_DEPTH_M`` of, or behind, a camera that
        sees it (module docstring). Those landmarks leave the window at the next update."""
        if not len(self._views):
            return []
        theta = self._theta
        keys, pose_keys, point_keys = _split_keys(theta)
        found = [keys[np.minimum(np.searchsorted(keys, self._views[:, c]), len(keys) - 1)] == self._views[:, c]
                 for c in (1, 2)]
        views = self._views[found[0] & found[1]]
        poses, points = gtsam.utilities.extractPose3(theta), gtsam.utilities.extractPoint3(theta)
        if len(poses) != len(pose_keys) or len(points) != len(point_keys):
            return []                               # a variable of another kind: the rows would not match the keys
        camera = poses[np.searchsorted(pose_keys, views[:, 1])]     # rows: R row-major (9), t (3)
        point = points[np.searchsorted(point_keys, views[:, 2])]
        depth = np.einsum('ij,ij->i', camera[:, [2, 5, 8]], point - camera[:, 9:])
        bad = ~(depth >= self.MIN_DEPTH_M)
        if not bad.any():
            return []
        dropped = np.unique(views[bad, 2])
        for m in dropped:
            self._stamps[int(m)] = -math.inf    # held by its own prior until then
        self.dropped.extend(int(m) for m in dropped)
        return [int(i) for i in views[np.isin(views[:, 2], dropped), 0]]
