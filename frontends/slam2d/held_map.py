"""A new run's keyframe graph solved against a saved map held where it is (`replay LOG --map SESSION`).

Localization must leave the saved map as it is, yet a run matched scan by scan against that map knows
nothing where the map saw nothing: it is tracked there, and drifts. The SLAM of the same run, resumed on the
saved keyframe graph (`frontends.slam2d.resume`), knows more: its scans are matched on its own recent
keyframes, and its loop closures tie it to itself where it drives a stretch twice and to the saved keyframes
wherever it sees them. Its joint graph, solved with the saved keyframes held at their saved poses, places the
new run in the saved map without moving the map.

Holding them is exact: the saved keyframes leave the graph, pose 0 stands for the map's origin, and a
constraint from saved keyframe a to new keyframe b (z, Ω) becomes one from the origin to b measuring x_a·z
with the same Ω: its error z⁻¹·(x_a⁻¹·x_b) is unchanged. The SLAM only adds constraints from an older
keyframe to a newer one, so no constraint runs from a new keyframe to a saved one; constraints between saved
keyframes are dropped (nothing they tie can move).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from frontends.errors import FrontendError
from frontends.protocol import BoolArray, FloatArray, IntArray
from frontends.slam2d.localization import LocalizedScan
from frontends.slam2d.resume import ResumedSlam2D
from optimizer import se2
from optimizer.benchmark_graphs import odometry_chain
from optimizer.graph import PoseGraph
from optimizer.solve import DEFAULT_METHOD, optimize

__all__ = ["HELD_MAP_AGREEMENT", "HeldMapProblem", "HeldMapScans", "HeldMapSolution", "HeldMapSolver",
           "HeldMapTrajectory", "HeldOdometry", "held_map_problem", "held_map_scans", "held_map_trajectory",
           "solve_held_map", "solve_with_map_held"]

HELD_MAP_AGREEMENT = 0.5
"""The median distance (m) at most between the held-map poses and a localizer's own poses of the scans it
matched to the saved map, for the former to be given (`held_map_trajectory`). The second halves of ACES,
CSAIL, FR079, Intel and the mumble loop in their first halves' maps: 0.011–0.033 m
(`benchmarks/sessions_bench.py`); 0.5 m off, the two placed the run differently (a look-alike place), and
the one matched scan by scan is the one to keep."""


class HeldOdometry:
    """The odometry the run's own SLAM gets with each scan given to the localizer (`of`): the wheels';
    without them, once the run is placed, the scan's pose in the saved map where the localizer matched it
    there. The map measures the motion the wheels did not: without it, the SLAM of MIT's Killian Court log,
    localized in its own map, slid 2.5 m sideways through 20 scans without odometry along a corridor of
    look-alike doors, while the map matches stayed within 0.1 m of the full run."""

    def __init__(self) -> None:
        self._placed = False
        self._source: str | None = None
        """Where the last odometry given came from: "wheels" or "map"."""

    def of(self, odometry: FloatArray | None, interval: float,
           found: LocalizedScan) -> tuple[FloatArray | None, float, bool]:
        """The SLAM's odometry for a scan with wheel `odometry` (None: none) interpolated over `interval`
        (s) that the localizer `found`, its interval, and whether the SLAM's odometry restarts first (the
        source changed: the wheels' frame is not the map's)."""
        source = "wheels" if odometry is not None else "map" if self._placed and found.matched else None
        restart = source is not None and self._source is not None and source != self._source
        if source is not None:
            self._source = source
        self._placed = self._placed or found.localized
        if source == "map":
            return found.pose.copy(), 0.0, restart
        return odometry, interval, restart


@dataclass(frozen=True, eq=False)
class HeldMapSolution:
    poses: FloatArray
    """(K − held, 3) the new keyframes' poses in the saved map's frame."""
    converged: bool
    """The optimization met its convergence test (if not, `poses` are not an optimum and not to be given as
    one)."""


@dataclass(frozen=True, eq=False)
class HeldMapProblem:
    """A joint graph with its saved keyframes held, as a graph of its own: node 0 is the saved map's origin
    (held by the optimizer, as every graph's first pose), node i > 0 the i-th new keyframe."""

    graph: PoseGraph
    """Its estimate is the online one: the joint graph's, moved rigidly onto the held keyframes."""
    odometry_start: FloatArray
    """(1 + new, 3) the new keyframes chained by their odometry constraints alone from the first one's
    online pose: what the run believed before any loop closure and any match with the map (the paper's
    poor start)."""
    keyframe_scans: tuple[FloatArray, ...]
    """Each node's points in its own frame (the origin's none), for a recording of the walls."""

    def starts(self) -> dict[str, FloatArray]:
        """The starts optimized, as a keyframe graph's final optimization has them (`optimizer.solve`):
        the lowest final χ² wins."""
        return {"odometry": self.odometry_start, "online": self.graph.poses}


HeldMapSolver = Callable[[HeldMapProblem], HeldMapSolution]
"""What optimizes a `HeldMapProblem` (`solve_held_map`, or one that also records the iterations)."""


def held_map_problem(graph: PoseGraph, held_poses: FloatArray,
                     keyframe_scans: Sequence[FloatArray] = ()) -> HeldMapProblem:
    """The joint `graph` (its first keyframes the saved map's) with the saved keyframes held at
    `held_poses`; `keyframe_scans`, when given, are every keyframe's points (saved ones first).

    Raises `FrontendError` when a constraint runs from a new keyframe to a saved one, or when no constraint
    ties the new keyframes to the saved ones."""
    held_poses = np.asarray(held_poses, dtype=np.float64).reshape(-1, 3)
    held = len(held_poses)
    edge_from, edge_to = graph.edge_from, graph.edge_to
    if np.any((edge_from >= held) & (edge_to < held)):
        raise FrontendError("a constraint runs from a new keyframe to a saved one: the saved map cannot be "
                            "held with it")
    crossing = (edge_from < held) & (edge_to >= held)
    if not crossing.any():
        raise FrontendError("no constraint ties the new keyframes to the saved map")
    new = (edge_from >= held) & (edge_to >= held)
    measurements = np.concatenate([se2.compose(held_poses[edge_from[crossing]], graph.measurements[crossing]),
                                   graph.measurements[new]])
    nodes_from = np.concatenate([np.zeros(int(crossing.sum()), dtype=np.int64), edge_from[new] - held + 1])
    nodes_to = np.concatenate([edge_to[crossing], edge_to[new]]) - held + 1
    information = np.concatenate([graph.information[crossing], graph.information[new]])
    onto_map = se2.rigid_fit(graph.poses[:held], held_poses)
    online = np.vstack([np.zeros((1, 3)), se2.compose(onto_map, graph.poses[held:])])
    reduced = PoseGraph.build(np.arange(len(online)), online, nodes_from, nodes_to, measurements, information,
                              check_information=False)
    scans = tuple(keyframe_scans[held:]) if len(keyframe_scans) else ((np.zeros((0, 2)),) * (len(online) - 1))
    # The new keyframes chained from the first one's online pose (the origin stays where it is).
    chain = np.vstack([online[:1], odometry_chain(reduced.from_pose(1))])
    return HeldMapProblem(reduced, chain, (np.zeros((0, 2)), *scans))


def solve_held_map(problem: HeldMapProblem) -> HeldMapSolution:
    """`problem` optimized by the default method from its starts (`HeldMapProblem.starts`)."""
    run = optimize(problem.graph, method=DEFAULT_METHOD, starts=problem.starts())
    for _ in run:
        pass
    return HeldMapSolution(np.array(run.result.poses[1:]), run.result.converged)


def solve_with_map_held(graph: PoseGraph, held_poses: FloatArray) -> HeldMapSolution:
    """The poses of keyframes `len(held_poses)`… of the joint `graph` (its first keyframes the saved map's),
    optimized with the saved keyframes at `held_poses` (`held_map_problem`: raises `FrontendError` when
    they cannot be held; `solve_held_map`)."""
    return solve_held_map(held_map_problem(graph, held_poses))


@dataclass(frozen=True, eq=False)
class HeldMapScans:
    """A resumed SLAM's new scans placed by its joint graph solved with the saved map held."""

    stamps_ns: IntArray
    """The new scans from the one the run was placed at (those before have no pose here)."""
    poses: FloatArray
    """(S, 3) their poses in the saved map's frame."""
    converged: bool
    keyframes: int
    """The new run's keyframes."""
    old_new_constraints: int
    """The constraints tying them to the saved keyframes (the placement's included)."""


def held_map_scans(resumed: ResumedSlam2D, held_poses: FloatArray,
                   solver: HeldMapSolver = solve_held_map) -> HeldMapScans:
    """`resumed` (resumed on the saved keyframes at `held_poses`) finished, and its new scans posed by
    `solver`. Raises `MapPlacementError` when the run was never placed."""
    held_poses = np.asarray(held_poses, dtype=np.float64).reshape(-1, 3)
    joint = resumed.finish()
    solution = solver(held_map_problem(joint.graph, held_poses, joint.keyframe_scans))
    keyframes = np.vstack([held_poses, solution.poses])
    graph, held = joint.graph, len(held_poses)
    crossing = int(np.sum((graph.edge_from < held) & (graph.edge_to >= held)))
    new = joint.scan_keyframes >= held
    return HeldMapScans(joint.scan_stamps_ns[new], joint.scan_poses(keyframes)[new], solution.converged,
                        len(solution.poses), crossing)


@dataclass(frozen=True, eq=False)
class HeldMapTrajectory:
    poses: FloatArray
    """(S, 3) every scan's held-map pose (NaN before the one the run was placed at)."""
    apart: float
    """The median distance (m) from the localizer's poses of the scans it matched (NaN: none matched)."""
    agrees: bool
    """Converged, checked against at least one map match, and within `HELD_MAP_AGREEMENT` of them."""


def held_map_trajectory(held: HeldMapScans, stamps_ns: IntArray, located: FloatArray,
                        matched: BoolArray) -> HeldMapTrajectory:
    """The held-map poses of a localized run's scans (`stamps_ns`, in log order; the held SLAM has every
    scan from the one it was placed at), checked against the localizer's poses `located` (S, 3) of the scans
    it `matched` to the saved map."""
    first = len(stamps_ns) - len(held.stamps_ns)
    if first < 0 or not np.array_equal(held.stamps_ns, np.asarray(stamps_ns)[first:]):
        raise FrontendError("the held-map SLAM's scans are not the localized ones")
    poses = np.full((len(stamps_ns), 3), np.nan)
    poses[first:] = held.poses
    both = np.asarray(matched, dtype=bool) & np.isfinite(poses[:, 0])
    if not both.any():
        return HeldMapTrajectory(poses, float("nan"), False)
    apart = float(np.median(np.hypot(*(poses[both, :2] - located[both, :2]).T)))
    return HeldMapTrajectory(poses, apart, held.converged and apart <= HELD_MAP_AGREEMENT)
