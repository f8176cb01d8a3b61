"""Do the 3D ambiguity test's capped rival registrations change any verdict? (issue 12, item 4: 3D speed)

    python benchmarks/rival_iterations_bench.py [--caps 30,10,6]

`loop_closure.verify_loop` on synthetic places, once per cap on the coarse rival registrations
(`loop_closure.RIVAL_ITERATIONS`): 40 town places (the town block of `tests.lidar_world`, four seeds; the
current scan up to 2 m and 10° from the candidate's) and 36 places on a featureless street with poles every
2–8 m (exactly periodic, or jittered by ±0.5 m): there a start a few metres away may reach a pole pattern
that fits as well. Prints the places where the verdicts differ and the tally of verdicts per cap.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from frontends.slam3d import loop_closure  # noqa: E402
from frontends.slam3d.config import LoopClosureConfig  # noqa: E402
from tests.lidar_world import (  # noqa: E402
    Lidar,
    homogeneous,
    planar_to_matrix,
    simulate_sweep,
    straight_street,
    town_loop,
)

SENSOR_HEIGHT = 1.8
POLE_PERIODS = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0)


def sweep(boxes: np.ndarray, x: float, y: float, yaw: float, seed: int) -> np.ndarray:
    """A still sweep from the planar pose, points in the sensor frame."""
    mount = homogeneous(np.eye(3), np.array([0.0, 0.0, SENSOR_HEIGHT]))
    pose = planar_to_matrix(np.array([x, y, yaw])) @ mount
    lidar = Lidar(columns=720)
    points, _ = simulate_sweep(boxes, np.repeat(pose[None], lidar.columns, axis=0), lidar,
                               np.random.default_rng(seed))
    return points.astype(np.float64)


def pole_street(period: float, jitter: float) -> np.ndarray:
    """The featureless street with 0.4 m poles along one kerb every `period` m (± `jitter`)."""
    rng = np.random.default_rng(1)
    along = np.arange(-100.0, 100.0, period)
    poles = [[x - 0.2, 4.0, 0.0, x + 0.2, 4.4, 5.0] for x in along + rng.uniform(-jitter, jitter, len(along))]
    return np.vstack([straight_street(), np.array(poles)])


def places() -> list[tuple[str, np.ndarray, tuple[float, float, float], tuple[float, float, float]]]:
    rng = np.random.default_rng(0)
    cases = []
    for seed in range(4):
        boxes = town_loop(seed).boxes
        for _ in range(10):
            x, y = rng.uniform(8, 32), rng.choice([0.0, 24.0])
            current = (x + rng.uniform(-2, 2), y + rng.uniform(-1, 1), math.radians(rng.uniform(-10, 10)))
            cases.append((f"town, seed {seed}", boxes, (x, y, 0.0), current))
    for period in POLE_PERIODS:
        for jitter in (0.0, 0.5):
            boxes = pole_street(period, jitter)
            for _ in range(3):
                x = rng.uniform(-20, 20)
                current = (x + rng.uniform(-2, 2), rng.uniform(-1, 1), math.radians(rng.uniform(-10, 10)))
                cases.append((f"poles every {period:g} m ± {jitter:g}", boxes, (x, 0.0, 0.0), current))
    return cases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--caps", default="30,10,6", help="rival iteration caps, comma-separated")
    args = parser.parse_args()
    caps = [int(cap) for cap in args.caps.split(",")]
    config = LoopClosureConfig()
    tally: dict[int, dict[str, int]] = {cap: {} for cap in caps}
    cases = places()
    differing = 0
    for index, (name, boxes, candidate, current) in enumerate(cases):
        target_points = sweep(boxes, *candidate, 2 * index)
        source_points = sweep(boxes, *current, 2 * index + 1)
        verdicts = []
        for cap in caps:
            loop_closure.RIVAL_ITERATIONS = cap
            target = loop_closure.RegistrationTarget(target_points, config)
            verdicts.append(loop_closure.verify_loop(target, source_points, [np.eye(4)], config).reason)
            tally[cap][verdicts[-1]] = tally[cap].get(verdicts[-1], 0) + 1
        if len(set(verdicts)) > 1:
            differing += 1
            print(f"- {name}: candidate {np.round(candidate, 2)}, current {np.round(current, 2)}: "
                  + ", ".join(f"{cap} iterations {v}" for cap, v in zip(caps, verdicts, strict=True)))
    print(f"\n{len(cases)} places, {differing} with differing verdicts\n")
    reasons = sorted({reason for counts in tally.values() for reason in counts})
    print("| rival iterations | " + " | ".join(reasons) + " |")
    print("|---" * (1 + len(reasons)) + "|")
    for cap in caps:
        print(f"| {cap} | " + " | ".join(str(tally[cap].get(reason, 0)) for reason in reasons) + " |")


if __name__ == "__main__":
    main()
