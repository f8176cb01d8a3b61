"""Place recognition (Scan Context) and geometric verification (GICP + ambiguity test) of loop closures."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import small_gicp

from frontends.slam3d.config import LoopClosureConfig
from frontends.slam3d.loop_closure import (
    RegistrationFit,
    RegistrationTarget,
    descriptor_distances,
    fit_information,
    registration_threads,
    scan_context,
    verify_loop,
)
from tests.lidar_world import Lidar, homogeneous, planar_to_matrix, simulate_sweep, straight_street, town_loop

CONFIG = LoopClosureConfig()
SENSOR_HEIGHT = 1.8


def sensor_pose(x: float, y: float, yaw: float) -> np.ndarray:
    return planar_to_matrix(np.array([x, y, yaw])) @ homogeneous(
        np.eye(3), np.array([0.0, 0.0, SENSOR_HEIGHT])
    )


def cloud_at(boxes: np.ndarray, pose: np.ndarray, seed: int = 0) -> np.ndarray:
    """A still sweep from `pose` (4×4), points in the sensor frame."""
    lidar = Lidar(columns=720)
    points, _ = simulate_sweep(
        boxes, np.repeat(pose[None], lidar.columns, axis=0), lidar, np.random.default_rng(seed)
    )
    return points.astype(np.float64)


def descriptor(points: np.ndarray) -> np.ndarray:
    return scan_context(points, CONFIG.descriptor_rings, CONFIG.descriptor_sectors, CONFIG.descriptor_radius)


def test_scan_context_recognises_a_place_seen_turned_and_finds_the_turn() -> None:
    world = town_loop()
    here = cloud_at(world.boxes, sensor_pose(20.0, 0.0, 0.0), seed=1)
    turned = cloud_at(world.boxes, sensor_pose(20.0, 0.3, math.radians(40.0)), seed=2)
    elsewhere = cloud_at(world.boxes, sensor_pose(20.0, 24.0, math.pi), seed=3)
    distances, headings = descriptor_distances(
        descriptor(turned), np.stack([descriptor(here), descriptor(elsewhere)])
    )
    sector = 2 * math.pi / CONFIG.descriptor_sectors
    assert headings[0] == pytest.approx(math.radians(40.0), abs=sector)
    assert distances[0] < 0.3
    assert distances[1] > distances[0] + 0.1


def test_verification_recovers_the_relative_pose_from_a_poor_guess() -> None:
    world = town_loop()
    candidate = sensor_pose(18.0, 0.0, 0.0)
    current = sensor_pose(19.5, 0.8, math.radians(6.0))
    target = RegistrationTarget(cloud_at(world.boxes, candidate, seed=4), CONFIG)
    verdict = verify_loop(target, cloud_at(world.boxes, current, seed=5), [np.eye(4)], CONFIG)
    assert verdict.reason == "accepted" and verdict.match is not None
    truth = np.linalg.inv(candidate) @ current
    np.testing.assert_allclose(verdict.match.relative[:3, 3], truth[:3, 3], atol=0.05)
    yaw = math.atan2(verdict.match.relative[1, 0], verdict.match.relative[0, 0])
    assert yaw == pytest.approx(math.radians(6.0), abs=math.radians(0.3))
    information = verdict.match.information
    np.testing.assert_allclose(information, information.T)
    assert np.linalg.eigvalsh(information).min() > 0
    assert verdict.match.inlier_fraction >= CONFIG.min_inlier_fraction


def test_a_featureless_street_is_ambiguous() -> None:
    street = straight_street()
    target = RegistrationTarget(cloud_at(street, sensor_pose(0.0, 0.0, 0.0), seed=6), CONFIG)
    verdict = verify_loop(target, cloud_at(street, sensor_pose(2.0, 0.0, 0.0), seed=7), [np.eye(4)], CONFIG)
    assert verdict.match is None and verdict.reason == "ambiguous"


class CountingTarget(RegistrationTarget):
    """Counts the full-resolution registrations (scored fits with their Hessian)."""

    fine_registrations = 0

    def register(self, source: small_gicp.PointCloud, guess: np.ndarray) -> RegistrationFit:
        self.fine_registrations += 1
        return super().register(source, guess)


def test_rivals_that_cannot_compete_are_not_registered_at_full_resolution() -> None:
    """A distinct corner: the six rival starts end back at the match or elsewhere with a poor fit, seen
    from their coarse registrations; only the guess is registered finely (seven registrations before)."""
    world = town_loop()
    target = CountingTarget(cloud_at(world.boxes, sensor_pose(18.0, 0.0, 0.0), seed=4), CONFIG)
    current = cloud_at(world.boxes, sensor_pose(19.5, 0.8, math.radians(6.0)), seed=5)
    verdict = verify_loop(target, current, [np.eye(4)], CONFIG)
    assert verdict.reason == "accepted"
    assert target.fine_registrations == 1


def test_a_competing_rival_is_registered_finely_and_rejects_the_match() -> None:
    """Along a featureless street the coarse rivals ahead and behind fit as well as the match: one is
    registered again at full resolution, and that fine fit makes the match ambiguous."""
    street = straight_street()
    target = CountingTarget(cloud_at(street, sensor_pose(0.0, 0.0, 0.0), seed=6), CONFIG)
    verdict = verify_loop(target, cloud_at(street, sensor_pose(2.0, 0.0, 0.0), seed=7), [np.eye(4)], CONFIG)
    assert verdict.reason == "ambiguous"
    assert target.fine_registrations == 2


def test_a_different_place_is_a_poor_fit() -> None:
    world = town_loop()
    target = RegistrationTarget(cloud_at(world.boxes, sensor_pose(18.0, 0.0, 0.0), seed=8), CONFIG)
    verdict = verify_loop(
        target, cloud_at(world.boxes, sensor_pose(20.0, 24.0, 0.0), seed=9), [np.eye(4)], CONFIG
    )
    assert verdict.match is None and verdict.reason == "poor fit"


def test_fit_information_keeps_the_fit_s_weak_directions_and_the_floors() -> None:
    hessian = np.diag([1e-3, 1e7, 1e7, 1e9, 1e9, 1e9])  # x barely constrained (a tunnel along x)
    information = fit_information(hessian, CONFIG)
    assert information[0, 0] < 1e-3 * information[1, 1]
    assert information[1, 1] <= CONFIG.min_sigma_linear**-2
    assert information[5, 5] <= CONFIG.min_sigma_angular**-2
    assert information[1, 1] > 0.5 * CONFIG.min_sigma_linear**-2  # a strong fit: the floor dominates


def test_a_verification_on_every_core_is_the_one_thread_verification() -> None:
    """`threads = 0` (the default) registers on every core the process may use: the same match as one
    thread, to rounding (the threads only split the sums of the Gauss–Newton steps)."""
    world = town_loop()
    candidate = cloud_at(world.boxes, sensor_pose(18.0, 0.0, 0.0), seed=4)
    current = cloud_at(world.boxes, sensor_pose(19.5, 0.8, math.radians(6.0)), seed=5)
    verdicts = []
    for threads in (1, 0):
        config = dataclasses.replace(CONFIG, threads=threads)
        verdicts.append(verify_loop(RegistrationTarget(candidate, config), current, [np.eye(4)], config))
    one, every = (verdict.match for verdict in verdicts)
    assert one is not None and every is not None
    np.testing.assert_allclose(every.relative, one.relative, atol=1e-6)
    assert every.inlier_fraction == pytest.approx(one.inlier_fraction, abs=1e-3)
    assert registration_threads(dataclasses.replace(CONFIG, threads=3)) == 3
    assert registration_threads(CONFIG) == len(os.sched_getaffinity(0))


@pytest.mark.parametrize(("user_policy", "spin_count"), [(None, "0"), ("ACTIVE", None)])
def test_small_gicp_threads_sleep_at_barriers_unless_the_user_chose(user_policy: str | None,
                                                                   spin_count: str | None) -> None:
    """small_gicp's libgomp is loaded passive (no spinning: beside a busy process, spinning threads doubled
    a replay's wall time) unless OMP_WAIT_POLICY says otherwise; the process's environment is left as it
    was. libgomp prints its settings at load with OMP_DISPLAY_ENV=verbose."""
    environment = {key: value for key, value in os.environ.items() if key != "OMP_WAIT_POLICY"}
    environment["OMP_DISPLAY_ENV"] = "verbose"
    if user_policy is not None:
        environment["OMP_WAIT_POLICY"] = user_policy
    program = ("import os, frontends.slam3d.loop_closure; "
               "print(os.environ.get('OMP_WAIT_POLICY'))")
    run = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120,
                         env=environment, cwd=Path(__file__).resolve().parents[1], check=True)
    assert run.stdout.strip() == str(user_policy)
    shown = [line.split("=")[1].strip().strip("'") for line in run.stderr.splitlines()
             if line.strip().startswith("GOMP_SPINCOUNT")]
    assert len(shown) == 1
    if spin_count is None:
        assert shown[0] != "0"
    else:
        assert shown[0] == spin_count
