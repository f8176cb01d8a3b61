"""Settings of `MapLocalizer` (localization in a saved 2D map): tracking, local re-acquisition, and the
whole-map search."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from frontends.slam2d.config import LoopClosureConfig
from frontends.slam2d.slam import BRANCH_AND_BOUND_LEVELS


@dataclass(frozen=True)
class LocalizationConfig:
    global_levels: int = BRANCH_AND_BOUND_LEVELS
    """Branch-and-bound pyramid levels of the whole-map search (the loop closures': one compiled kernel)."""
    global_resolution: float = 0.15
    """Cell size (m) of the grid the whole-map search runs on (its likelihood σ at least this): a building
    at 5 cm cells and 0.75° steps takes seconds per attempt, at 15 cm and 1° a fraction of one; ICP on the
    full-resolution map then refines the match."""
    global_angular_step: float = math.radians(1.0)
    global_margin: float = 2.0
    """The search covers the saved keyframes' bounding box plus this (m): the robot is where the mapping
    robot was, give or take a corridor's width."""
    global_max_points: int = 300
    """The whole-map search's query is thinned to at most this many points (evenly along it)."""
    min_query_keyframes: int = 4
    """Global localization tries the first scan alone at once, and if that is ambiguous waits until the
    scans since it started span this many keyframes (~1 m)."""
    retry_every_keyframes: int = 3
    """After a failed attempt, the next one waits this many keyframes: an attempt over a whole building
    costs tenths of a second to seconds, and the next keyframe mostly sees the same place."""
    attempts_before_backoff: int = 3
    """After this many failed attempts in a row the wait between two doubles at every failure …"""
    max_retry_keyframes: int = 24
    """… up to this many keyframes (~7 m): a robot driving where the map never was (a courtyard, another
    wing) would otherwise pay a whole-map search every metre, seconds each on a large map, for nothing."""
    lost_after_unmatched: int = 5
    """Predicted by constant velocity (no odometry, not even the scans' own: see `ScanOdometry`), tracking
    is lost after this many scans in a row matched nothing: localize globally again (a constant-velocity
    prediction is worth a few scans, not metres)."""
    max_dead_reckoning: float = 30.0
    """With odometry (the wheels', else the scans' own), scans that match nothing (the robot drove out of the
    saved map, or people hide the walls) keep the odometry's pose; tracking is declared lost only once it
    moved this far (m) since the last match scoring `min_tracking_score`, not counting the scans the rolling
    local map tracked (`count_rolling_tracks_near_map`): back in the map, the tracking window or the local
    re-acquisition finds the walls again, which a global search in a place the map does not show never would
    (and it costs seconds)."""
    min_tracking_score: float = 0.5
    """A tracked scan scoring below this on the map (a robot carried elsewhere can still match a look-alike
    corridor at 0.55–0.7; a corridor the map saw only from afar scores 0.2–0.4) counts as a miss: after
    `relocalize_after` misses the local re-acquisition looks for a better place. Its match still counts,
    weighed by `weak_match_weight`."""
    min_match_score: float = 0.2
    """Below this the scan's match is not used at all: too few of its points lie on the map."""
    weak_match_weight: float = 0.1
    """A match scoring below `min_tracking_score` weighs this much against the prediction (its points
    mostly fall where the map saw nothing, and the few that do not can pull it onto the wrong wall); and the
    wheels' prediction weighs this much against a match that overrules them (`MapLocalizer._match`)."""
    relocalize_after: int = 3
    """Local re-acquisition starts after this many misses in a row …"""
    relocalize_every: float = 0.3
    """… and is tried again every this many metres driven (m) while the misses go on."""
    relocalize_window: float = 0.5
    """Half-width of its search (m) at the first attempt …"""
    relocalize_window_per_metre: float = 0.1
    """… plus this per metre driven since the last good match (odometry drifts a few % of the distance) …"""
    max_relocalize_window: float = 4.0
    """… up to this (m), on the map's own grid. Beyond, the drift may have carried the true place out of
    any window capped short of it (one capped at 4 m accepted a look-alike inside it at Killian Court,
    after 270 m tracked outside the map: 9 m off, then matched there for 900 scans). Then a strong match
    of the saved map near the track is not taken (a look-alike stretch of corridor fits as well as the
    true one), and the re-acquisition searches the whole region the drift allows on the global
    localization's coarse grid (the same tests, the headings within `relocalize_angular`: over every
    heading, a query half outside the map fitted a corridor of it turned, 5 m off; while the map fits the
    newest scan near the track, that scan alone is the query: the scans before it may lie where the map
    never was, and kept the robot unplaced 2 m into the map). Its match is taken
    only when it lands where the track is, or moves the track as one found metres before did: one match
    that wide can be a look-alike of a place outside the map (CSAIL: 9.4 m off)."""
    wide_retry_share: float = 0.25
    """Such a wide attempt is tried again after driving this share of the region's half-width (at least
    `relocalize_every_outside`): each costs up to a whole-map search, and the region grows with the
    distance, so the attempts thin out with it. While the saved map fits the scan near the track, or a
    match waits for its confirmation, every `relocalize_every`."""
    relocalize_angular: float = math.radians(15.0)
    relocalize_keyframes: int = 6
    """The query of a local re-acquisition: the current scan and this many earlier ones, each at least
    `relocalize_every` metres from the next (a few metres of context; one scan of a corridor is
    ambiguous along it)."""
    rolling_map_length: float = 20.0
    """The rolling local map (slam_toolbox's localization mode keeps one too) holds the scans of the last
    this many metres driven, at their tracked poses; a scan the saved map cannot place (its match scores
    below `min_match_score`, or fails ICP's tests) is matched on it. Never written into the saved map. …"""
    rolling_map_spacing: float = 0.3
    """… one scan every this many metres (m) (or after a turn of 12°) …"""
    rolling_map_saved_keyframes: int = 10
    """… with the saved keyframes nearest to its newest scan, at most this many …"""
    rolling_map_reach: float = 10.0
    """… within this distance (m): where the robot leaves the saved map, the map's last walls and the
    new ones are matched together."""
    rolling_map_rebuild: float = 0.5
    """Its grid is built again only once the robot drove this far (m) since the last build (a build costs
    as much as a dozen matches; the scans that joined meanwhile overlap what it holds)."""
    map_reach: float = 3.0
    """A pose tracked on the rolling local map farther than this (m) from every saved keyframe is outside
    the saved map: local re-acquisition is tried there only every `relocalize_every_outside`, and it never
    counts towards `max_dead_reckoning` (nearer, see `count_rolling_tracks_near_map`)."""
    count_rolling_tracks_near_map: bool = False
    """Whether a pose tracked on the rolling local map within `map_reach` of a saved keyframe counts
    towards `max_dead_reckoning`. False (slam_toolbox's localization mode, AMCL): a scan the rolling local
    map explains is not dead reckoning anywhere, and the localizer is declared lost only after
    `max_dead_reckoning` metres that neither the saved map (matching well) nor the rolling local map
    explained. A first run that saw a part of the building only from afar leaves weak map matches there and
    rolling tracks beside its keyframes: counted, 40 m of them on CSAIL declared the robot lost, and the
    whole-map search then placed it 5 m off in a look-alike room. True: a robot carried elsewhere inside
    its map, whose scans keep fitting its own recent scans, is declared lost there and found again; with
    `map_reach` = inf everywhere (the price otherwise: a kidnapped estimate driving out of the map, through
    its walls, is tracked there on its own scans and never lost; a whole-map search there finds look-alike
    corridors: the north one of the test world in a map of the south one)."""
    relocalize_every_outside: float = 2.0
    """Local re-acquisition while tracked outside the saved map (`map_reach`) is tried only every this many
    metres: the map may still have seen the place from afar, but mostly there is nothing to find."""
    max_lost_keyframes: int = 300
    """While lost, the scans are tracked in their own frame; that track restarts after this many keyframes
    (only the last few make a query; the rest would only cost memory). The scans' own odometry of a log
    without wheel odometry (`ScanOdometry`) restarts its tracking as often."""
    odometry_noise_linear: float = 0.015
    """Wheel odometry's noise between two scans, σ (m) …"""
    odometry_noise_per_metre: float = 0.1
    """… plus this share of the distance driven …"""
    odometry_noise_angular: float = math.radians(0.6)
    """… and in heading σ (rad) …"""
    odometry_noise_angular_per_metre: float = math.radians(3.0)
    """… plus this per metre driven …"""
    odometry_noise_per_radian: float = 0.05
    """… plus this share of the turn. The pose's covariance grows by these along the odometry and shrinks
    with every match (`information_scale` × ICP's Hessian): the tracked pose is the covariance-weighted
    mean of the prediction and the match, so one weak match in a corridor the map saw only from afar moves
    it a little, not to wherever that match landed. (The SLAM's own odometry σ is the search window's, not
    a noise model: 5 cm and 2° per scan.)"""
    fix_sigma_linear: float = 0.1
    fix_sigma_angular: float = math.radians(2.0)
    """σ of a pose just placed (a global fix, a local re-acquisition, or the given initial pose)."""
    acceptance: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    """Score, ambiguity and ICP tests of a global match, and the query's keyframes and thinning: the loop
    closures' own settings."""
