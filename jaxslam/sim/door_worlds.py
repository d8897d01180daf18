"""Door scenarios of Avots et al. (IROS 2002): worlds whose doors open and close.

(a) :func:`corridors_scenario`, the two-corridor building of the paper's Fig. 2::

      y=15  +--------+ room behind D5 (same as D1's)
            |        |
      y=12  +---+ D5 +------------------------------------------+   corridor B
            |                                                   |   (walls only at D2, D3, D4's places)
      y=10  +---------------------------------------------------+
                 R1        R2         R3            R4
      y=5   +--------+ +--------+ +--------+     +--------+
            |        | |        | |        |     |        |
      y=2   +---+ D1 +-+--+ D2 +-+--+ D3 +-------+-+ D4 +--+   corridor A (the robot's)
            |  1a -->                                  4a   |
      y=0   +---------------------------------------------------+
            x=0                                                x=20

   Two corridors with the same walls, ends and length, 10 m apart (a sensor never
   sees one from the other). Corridor A has doors D1..D4 in its north wall, each
   into a 3 m x 3 m room; corridor B has a door D5 at D1's place (into an
   identical room) and plain wall where A has D2, D3, D4. So the corridors differ
   *only* in their doors. The map given to the filter says every door is open
   (initial belief 0.6). In truth D1, D4, D5 are open and D2, D3 closed: from
   1a (near D1) to D3 the sensor sees exactly what it would see in corridor B,
   and B matches the *map* better (no opening where the map has one). Only D4,
   open, at 4a tells the corridors apart, and only a filter that kept the
   corridor-A hypothesis alive (by explaining the unbroken wall with closed
   doors, paying the prior once rather than at every scan) can use it. The
   filter starts uniform over the first 5 m of both corridors.

(b) :func:`office_doors_scenario`, the office pass of Fig. 1: a corridor with
   six doors (three per side, each into a room). The robot drives out with every
   door closed; at the far end, while it turns, four doors open; it drives back.
   The filter starts tracked (uniform within 0.3 m and 0.15 rad of the true start).

(c) :func:`patrol_doors_scenario`, for learning the doors' transition model: the corridor of
   (b) driven out and back many times while the doors open and close at random.

All return a :class:`DoorScenario`: the true world (and door states per step),
the :class:`~jaxslam.localization.doors.DoorMap` given to the filter, the true path and a
:class:`~jaxslam.laserlog.LaserLog` (noisy odometry and ranges), deterministic
given the key.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.laser import SensorSpec, make_sensor, uniform_beams
from jaxslam.laserlog import LaserLog
from jaxslam.localization import doors
from jaxslam.localization.beam_model import make_beam_model_params
from jaxslam.localization.doors import DoorMap, make_door_map
from jaxslam.localization.mcl import MclConfig
from jaxslam.motion import MotionParams, motion_params
from jaxslam.segment_map import expected_ranges
from jaxslam.sim.paths import concat_paths, waypoint_path
from jaxslam.sim.simulate import simulate_log
from jaxslam.sim.world import SegmentWorld, make_world, wall_segments

DOOR_WIDTH = 1.0
"""Width (m) of every door opening."""
ROOM_SIZE = 3.0
"""Width and depth (m) of the room behind a door."""


@dataclasses.dataclass(frozen=True, eq=False)
class DoorScenario:
    """A simulated run through a world with doors."""

    name: str
    world: SegmentWorld
    """The true world: walls, then the K doors (group "doors"; segment W + k is door k)."""
    true_door_open: np.ndarray
    """(T, K) bool: door k open in truth at scan t."""
    door_map: DoorMap
    """The map given to the filter (true geometry; its own initial beliefs and transitions)."""
    door_names: tuple[str, ...]
    """Label of each door ("D1", ...)."""
    true_poses: np.ndarray
    """(T, 3) float64 true robot poses."""
    log: LaserLog
    """Noisy odometry and ranges, with the true poses as ground truth."""
    observed_doors: np.ndarray
    """(T, K) bool: some beam of the true scan at t reached door k first (open or closed)."""
    start_regions: np.ndarray
    """(R, 4) boxes [xmin, ymin, xmax, ymax] (m) for a global initialisation."""
    heading_range: tuple[float, float]
    """Heading interval (rad) of the global initialisation."""
    start_std: np.ndarray
    """(3,) std (m, m, rad) of a tracked initialisation around the first true pose."""

    @property
    def num_doors(self) -> int:
        return int(self.true_door_open.shape[1])

    @property
    def num_scans(self) -> int:
        return int(self.true_poses.shape[0])


def door_sensor(num_beams: int = 61, fov_deg: float = 180.0, range_max: float = 10.0) -> SensorSpec:
    """The scenarios' laser: ``num_beams`` beams over ``fov_deg`` degrees, ``range_max`` metres."""
    return make_sensor(uniform_beams(num_beams, np.deg2rad(fov_deg)), 0.0, range_max)


def filter_settings(scenario: DoorScenario, num_particles: int = 1000, beam_stride: int = 2
                    ) -> tuple[doors.DoorConfig, doors.DoorParams]:
    """The door filters' settings for these scenarios: a beam model with sigma_hit = 0.2 m,
    likelihood gain 0.1 (31 of 61 beams, treated as about 3 independent ones: a particle cloud of
    0.6 m x 0.3 rad does not collapse on the first scan), resampling at ESS < 0.5 N, the map's
    door transitions."""
    config = doors.DoorConfig(MclConfig(num_particles=num_particles, beam_stride=beam_stride))
    params = doors.make_params(scenario.door_map, beam=make_beam_model_params(sigma_hit=0.2), likelihood_gain=0.1,
                               resample_threshold=0.5)
    return config, params


def scenario_motion_params() -> MotionParams:
    """Odometry noise used to simulate the logs (the filters assume the default of
    :func:`jaxslam.localization.mcl.make_params`, which is larger)."""
    return motion_params(0.02, 0.01, 0.02, 0.02, 0.005, 0.002)


def _room(cx: float, wall_y: float, side: float) -> np.ndarray:
    """The three walls (3, 4) of a room centred at x = ``cx`` behind a wall at ``wall_y``,
    on the side ``side`` (+1 north, -1 south)."""
    h = ROOM_SIZE / 2
    far = wall_y + side * ROOM_SIZE
    return np.array([[cx - h, wall_y, cx - h, far], [cx - h, far, cx + h, far], [cx + h, far, cx + h, wall_y]],
                    np.float32)


def _door(cx: float, wall_y: float) -> np.ndarray:
    return np.array([cx - DOOR_WIDTH / 2, wall_y, cx + DOOR_WIDTH / 2, wall_y], np.float32)


def _corridor(y0: float, length: float, north_doors, south_doors=(), width: float = 2.0):
    """Walls (with gaps) of a corridor [0, length] x [y0, y0 + width], rooms behind the gaps, and
    the door segments (north doors first)."""
    y1 = y0 + width
    walls = [
        wall_segments((0.0, y0), (length, y0), [(x, DOOR_WIDTH) for x in south_doors]),
        wall_segments((0.0, y1), (length, y1), [(x, DOOR_WIDTH) for x in north_doors]),
        np.array([[0.0, y0, 0.0, y1], [length, y0, length, y1]], np.float32),
    ]
    walls += [_room(x, y1, +1.0) for x in north_doors] + [_room(x, y0, -1.0) for x in south_doors]
    doors = [_door(x, y1) for x in north_doors] + [_door(x, y0) for x in south_doors]
    return np.concatenate(walls, axis=0), np.stack(doors)


def _observed(segments: np.ndarray, num_walls: int, num_doors: int, poses: np.ndarray,
              sensor: SensorSpec) -> np.ndarray:
    """(T, K): which doors the true scans reach before any wall (every door cast as closed)."""

    def one(pose):
        _, hit = expected_ranges(jnp.asarray(segments), pose, sensor)
        return jnp.zeros(num_doors + 1, bool).at[jnp.where(hit >= num_walls, hit - num_walls, num_doors)].set(True)

    return np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(poses, jnp.float32)))[:, :num_doors]


def _build(key, name, walls, doors, true_open, poses, sensor, door_map, start_regions, heading_range,
           start_std, door_names, range_noise_std, dt=0.25) -> DoorScenario:
    num_walls, num_doors = walls.shape[0], doors.shape[0]
    segments = np.concatenate([walls, doors], axis=0)
    world = make_world(segments, groups={"walls": np.arange(num_walls),
                                         "doors": num_walls + np.arange(num_doors)})
    active = np.concatenate([np.ones((poses.shape[0], num_walls), bool), ~true_open], axis=1)
    log = simulate_log(key, world, poses, sensor, scenario_motion_params(), range_noise_std, dt=dt,
                       active=active, source=f"<{name} scenario>")
    observed = _observed(segments, num_walls, num_doors, poses, sensor)
    return DoorScenario(name, world, true_open, door_map, tuple(door_names), poses, log, observed,
                        np.asarray(start_regions, np.float32), heading_range, np.asarray(start_std, np.float32))


def corridors_scenario(key, step_length: float = 0.2, num_beams: int = 61, range_noise_std: float = 0.03,
                       map_initial_open: float = 0.6, p_open_open: float = 0.997,
                       p_open_closed: float = 0.003, start_box: float = 0.3,
                       start_heading: float = 0.15) -> DoorScenario:
    """Scenario (a): two corridors that differ only in their doors (see the module docstring).

    Doors: D1..D4 in corridor A (x = 3, 7.5, 11, 16 on its north wall y = 2), D5 in corridor B
    (x = 3, y = 12). Truth: D2, D3 closed, the others open, at every scan. The map says every
    door is open (``map_initial_open``). The robot drives from 1a (1.5, 1) east to 4a (18, 1).

    Args:
      key: PRNG key (ranges and odometry noise).
      step_length: metres driven per scan.
      num_beams: beams over 180 degrees.
      range_noise_std: range noise (m).
      map_initial_open: the map's belief that each door is open.
      p_open_open, p_open_closed: the map's door transition probabilities per scan.
    """
    length = 20.0
    walls_a, doors_a = _corridor(0.0, length, north_doors=(3.0, 7.5, 11.0, 16.0))
    walls_b, doors_b = _corridor(10.0, length, north_doors=(3.0,))
    # Corridor B's plain north wall where A has D2..D4 is already one segment (no gaps there).
    walls = np.concatenate([walls_a, walls_b], axis=0)
    doors = np.concatenate([doors_a, doors_b], axis=0)
    poses = waypoint_path([(1.5, 1.0), (18.0, 1.0)], step_length, 0.3)
    poses = np.concatenate([np.array([[1.5, 1.0, 0.0]]), poses], axis=0)
    open_now = np.array([True, False, False, True, True])
    true_open = np.broadcast_to(open_now, (poses.shape[0], 5)).copy()
    door_map = make_door_map(walls, doors, map_initial_open, p_open_open, p_open_closed)
    # The robot knows where it is up to the corridor: a box of +-start_box m around 1a in each.
    x0, y0 = poses[0, :2]
    regions = [(x0 - start_box, y0 + dy - start_box, x0 + start_box, y0 + dy + start_box) for dy in (0.0, 10.0)]
    return _build(key, "corridors", walls, doors, true_open, poses, door_sensor(num_beams), door_map, regions,
                  (-start_heading, start_heading), (0.1, 0.1, 0.05), ("D1", "D2", "D3", "D4", "D5"), range_noise_std)


def office_doors_scenario(key, step_length: float = 0.2, num_beams: int = 61, range_noise_std: float = 0.03,
                          p_open_open: float = 0.997, p_open_closed: float = 0.003) -> DoorScenario:
    """Scenario (b): the office pass of Fig. 1. A 20 m corridor with doors D1..D3 on its north wall
    (x = 4, 9, 14) and D4..D6 on its south wall (x = 6.5, 11.5, 16.5). All closed on the way out
    ((1.5, 1) -> (18.5, 1)); while the robot turns round at the far end, D1, D2, D4, D5 open; then
    it drives back to (1.5, 1). The map knows the geometry, not the states (initial belief 0.5).
    """
    length = 20.0
    walls, doors = _corridor(0.0, length, north_doors=(4.0, 9.0, 14.0), south_doors=(6.5, 11.5, 16.5))
    out = waypoint_path([(1.5, 1.0), (18.5, 1.0)], step_length, 0.3)
    out = np.concatenate([np.array([[1.5, 1.0, 0.0]]), out], axis=0)
    back = waypoint_path([(18.5, 1.0), (1.5, 1.0)], step_length, 0.3, start_heading=0.0)
    poses = concat_paths(out, np.concatenate([out[-1:], back], axis=0))
    turn_end = out.shape[0] + int(np.ceil(np.pi / 0.3))  # the scan at which the turn on the spot is over
    true_open = np.zeros((poses.shape[0], 6), bool)
    true_open[turn_end - 8:, [0, 1, 3, 4]] = True  # opened during the turn
    door_map = make_door_map(walls, doors, 0.5, p_open_open, p_open_closed)
    x0, y0 = poses[0, :2]
    regions = [(x0 - 0.3, y0 - 0.3, x0 + 0.3, y0 + 0.3)]  # tracked: the start is known to +-0.3 m, +-0.15 rad
    return _build(key, "office", walls, doors, true_open, poses, door_sensor(num_beams), door_map, regions,
                  (-0.15, 0.15), (0.1, 0.1, 0.05), tuple(f"D{i}" for i in range(1, 7)), range_noise_std)


def markov_door_states(key, num_scans: int, num_doors: int, p_open_closed: float, p_closed_open: float
                       ) -> np.ndarray:
    """(num_scans, num_doors) bool door states from a two-state Markov chain per door: a closed
    door opens with probability ``p_open_closed`` at each scan, an open one closes with
    ``p_closed_open``; the first scan's states are drawn from the chain's stationary law."""
    if not (0.0 < p_open_closed < 1.0 and 0.0 < p_closed_open < 1.0):
        raise ValueError(f"markov_door_states: transition probabilities must be in (0, 1), got "
                         f"p_open_closed={p_open_closed}, p_closed_open={p_closed_open}")
    uniforms = np.asarray(jax.random.uniform(key, (num_scans, num_doors)), np.float64)
    stationary_open = p_open_closed / (p_open_closed + p_closed_open)
    states = np.empty((num_scans, num_doors), bool)
    states[0] = uniforms[0] < stationary_open
    for t in range(1, num_scans):  # host-side simulation of the truth, once per scenario
        p_open = np.where(states[t - 1], 1.0 - p_closed_open, p_open_closed)
        states[t] = uniforms[t] < p_open
    return states


def patrol_doors_scenario(key, num_round_trips: int = 10, step_length: float = 0.2, num_beams: int = 61,
                          range_noise_std: float = 0.03, p_open_closed: float = 0.01,
                          p_closed_open: float = 0.01) -> DoorScenario:
    """Scenario (c), for learning the doors' transition model: the office corridor of (b), driven
    out and back ``num_round_trips`` times, while every door opens and closes at random as a
    Markov chain (:func:`markov_door_states`; per scan, a closed door opens with
    ``p_open_closed``, an open one closes with ``p_closed_open``; 0.01 each: a door keeps its
    state for 100 scans on average, about half a round trip). The map's transition model is
    the truth; the filter starts tracked as in (b). About 190 scans per round trip.
    """
    if num_round_trips < 1:
        raise ValueError(f"patrol_doors_scenario: num_round_trips must be >= 1, got {num_round_trips}")
    length = 20.0
    walls, doors = _corridor(0.0, length, north_doors=(4.0, 9.0, 14.0), south_doors=(6.5, 11.5, 16.5))
    west, east = (1.5, 1.0), (18.5, 1.0)
    out = waypoint_path([west, east], step_length, 0.3)
    poses = np.concatenate([np.array([[*west, 0.0]]), out], axis=0)
    for trip in range(num_round_trips):
        back = waypoint_path([east, west], step_length, 0.3, start_heading=0.0)
        poses = concat_paths(poses, np.concatenate([poses[-1:], back], axis=0))
        if trip < num_round_trips - 1:
            again = waypoint_path([west, east], step_length, 0.3, start_heading=np.pi)
            poses = concat_paths(poses, np.concatenate([poses[-1:], again], axis=0))
    k_doors, k_log = jax.random.split(key)
    true_open = markov_door_states(k_doors, poses.shape[0], doors.shape[0], p_open_closed, p_closed_open)
    door_map = make_door_map(walls, doors, 0.5, 1.0 - p_closed_open, p_open_closed)
    x0, y0 = poses[0, :2]
    regions = [(x0 - 0.3, y0 - 0.3, x0 + 0.3, y0 + 0.3)]
    return _build(k_log, "patrol", walls, doors, true_open, poses, door_sensor(num_beams), door_map, regions,
                  (-0.15, 0.15), (0.1, 0.1, 0.05), tuple(f"D{i}" for i in range(1, 7)), range_noise_std)


SCENARIOS = {"corridors": corridors_scenario, "office": office_doors_scenario, "patrol": patrol_doors_scenario}
"""Scenario builders by name (the CLI's ``--scenario``)."""
