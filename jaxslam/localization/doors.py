"""Localization with door-state estimation (Avots, Lim, Thibaux & Thrun, IROS 2002).

A door map is static walls plus K doors, each a segment with an id, an initial
belief p(open) and a transition model p(open | open), p(open | closed)
(:class:`DoorMap`). The hybrid filter keeps, per particle, a pose and the K
probabilities pi_k that door k is open, conditioned on that particle's path.
Per step (docs/design.md, "Door-state estimation"):

1. move the poses (:func:`jaxslam.motion.sample`) and predict every door,
   pi+ = p(open|open) pi + p(open|closed) (1 - pi)            (Eq. 24);
2. cast the scan against walls + all doors (all closed): a beam whose first hit
   is door k is *attributed* to door k; its closed-door range is that hit. Cast
   it again with door k alone made transparent: the range with door k open
   (the next wall, or another door behind it taken as closed). Beams that hit
   a wall (or nothing) first give the static likelihood;
3. L_k(open), L_k(closed): the products of the beam-model likelihoods of door
   k's beams; weight p(z_static | x) prod_k [L_k(open) pi+_k + L_k(closed) (1 - pi+_k)]
   (Eq. 33); door posterior pi_k = L_k(open) pi+_k / (...)   (Eqs. 27-28).
   A door no beam reaches keeps pi+_k (it drifts toward the stationary value);
4. resample poses together with their door beliefs.

Cost per particle and beam: two casts against W + K segments, a segment-sum of
the beams into K doors and K binary updates: linear in K. The second cast makes
only the attributed door transparent, rather than all doors (a cast against the
walls alone, which is cheaper), so that a beam that passes an open door and then
meets a second door (connecting rooms) is scored against that door, taken as
closed, instead of against the wall behind it: the factorisation attributes each
beam to exactly one door, and this is the exact likelihood of "door k open, the
others closed". When no beam path crosses two doors, both choices agree.

Baselines: static MCL on the map as given (:func:`static_segments` with
:mod:`jaxslam.localization.mcl`), and door-aware MCL without memory (``DoorConfig(memory=False)``:
every door is 50% open before every update, which equals the hybrid filter
with p(open|open) = p(open|closed) = 0.5; a test pins that down). Running them over many
seeds and scoring them against the truth is the experiment's (experiments/door_harness.py).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import binary_bayes, particle_filter
from jaxslam import motion as motion_model
from jaxslam.laser import SensorSpec, laser_rays, subsample_beams
from jaxslam.localization import mcl
from jaxslam.localization.beam_model import BeamModelParams, beam_model_log_likelihood
from jaxslam.localization.mcl import MclConfig, MclInfo, ScanInputs
from jaxslam.motion import MotionParams
from jaxslam.segment_map import raycast


class DoorMap(NamedTuple):
    """Walls and doors (a pytree of arrays: traced)."""

    walls: Float[Array, "W 4"]
    """(W, 4) static segments [x1, y1, x2, y2] (m)."""
    doors: Float[Array, "K 4"]
    """(K, 4) door segments (m): the door leaf when closed; transparent when open."""
    door_ids: Int[Array, "K"]
    """An id per door (for plots and reports)."""
    initial_open: Float[Array, "K"]
    """Initial belief p(open) of each door."""
    p_open_open: Float[Array, "K"]
    """p(open_t | open_{t-1}) per door, per step."""
    p_open_closed: Float[Array, "K"]
    """p(open_t | closed_{t-1}) per door, per step."""

    @property
    def num_doors(self) -> int:
        return int(self.doors.shape[0])

    @property
    def num_walls(self) -> int:
        return int(self.walls.shape[0])


def make_door_map(walls, doors, initial_open=0.5, p_open_open=0.99, p_open_closed=0.01,
                  door_ids=None) -> DoorMap:
    """A :class:`DoorMap` of float32 arrays; scalars broadcast to every door; ids default to 1..K."""
    walls = jnp.asarray(walls, jnp.float32).reshape(-1, 4)
    doors = jnp.asarray(doors, jnp.float32).reshape(-1, 4)
    k = doors.shape[0]
    per_door = lambda v: jnp.broadcast_to(jnp.asarray(v, jnp.float32), (k,))  # noqa: E731
    ids = jnp.arange(1, k + 1, dtype=jnp.int32) if door_ids is None else jnp.asarray(door_ids, jnp.int32)
    return DoorMap(walls, doors, ids, per_door(initial_open), per_door(p_open_open), per_door(p_open_closed))


def all_segments(door_map: DoorMap) -> Float[Array, "M 4"]:
    """(W + K, 4): the walls, then the doors (segment W + k is door k)."""
    return jnp.concatenate([door_map.walls, door_map.doors], axis=0)


def static_segments(door_map: DoorMap, door_open: Bool[Array, "K"] | None = None
                    ) -> tuple[Float[Array, "M 4"], Bool[Array, "M"]]:
    """Segments and (W + K,) active mask of the map as given: a door is present (closed) when its
    ``initial_open`` is below 0.5, unless ``door_open`` says otherwise. For static MCL."""
    if door_open is None:
        door_open = door_map.initial_open >= 0.5
    active = jnp.concatenate([jnp.ones(door_map.num_walls, bool), ~jnp.asarray(door_open, bool)])
    return all_segments(door_map), active


@dataclasses.dataclass(frozen=True)
class DoorConfig:
    """Static settings (shapes and code paths). Hashable; changing it recompiles."""

    mcl: MclConfig = dataclasses.field(default_factory=MclConfig)
    """The particle set's settings, as for static MCL (and checked there): N particles (each
    with a pose and K door beliefs), the beam stride, the resampler."""
    memory: bool = True
    """False: the memoryless baseline, every door 50% open before every update (the
    stored beliefs and the transition model are ignored)."""

    def __post_init__(self):
        if not isinstance(self.mcl, MclConfig):
            raise TypeError(f"DoorConfig: mcl must be an MclConfig, got {self.mcl!r}")


class DoorParams(NamedTuple):
    """Traced numbers: changing them never recompiles; they can be differentiated."""

    motion: MotionParams
    """Odometry noise coefficients."""
    beam: BeamModelParams
    """Beam model mixture weights, sigma_hit (m), lambda_short (1/m)."""
    likelihood_gain: Float[Array, ""]
    """Multiplier of every beam's log-likelihood (applied before the door mixture, so the
    door posterior and the weights use the same tempered likelihoods)."""
    resample_threshold: Float[Array, ""]
    """Resample when ESS < resample_threshold * N."""
    p_open_open: Float[Array, "K"]
    """p(open_t | open_{t-1}) per door, per step."""
    p_open_closed: Float[Array, "K"]
    """p(open_t | closed_{t-1}) per door, per step."""

    def mcl_params(self) -> mcl.MclParams:
        """The shared numbers, for static MCL."""
        return mcl.MclParams(self.motion, self.beam, self.likelihood_gain, self.resample_threshold)


def make_params(door_map: DoorMap, motion: MotionParams | None = None, beam: BeamModelParams | None = None,
                likelihood_gain=0.5, resample_threshold=0.5) -> DoorParams:
    """:class:`DoorParams` with the door map's transition probabilities."""
    base = mcl.make_params(motion, beam, likelihood_gain, resample_threshold)
    return DoorParams(base.motion, base.beam, base.likelihood_gain, base.resample_threshold,
                      door_map.p_open_open, door_map.p_open_closed)


def memoryless_params(params: DoorParams) -> DoorParams:
    """``params`` with p(open|open) = p(open|closed) = 0.5: every prediction is 50% open."""
    half = jnp.full_like(params.p_open_open, 0.5)
    return params._replace(p_open_open=half, p_open_closed=half)


class DoorState(NamedTuple):
    """The particle set of the hybrid filter."""

    poses: Float[Array, "N 3"]
    """Pose of each particle [x, y, theta] (m, m, rad)."""
    door_open: Float[Array, "N K"]
    """Each particle's probability that door k is open, given its path and the scans so far."""
    log_weights: Float[Array, "N"]
    """Normalised log-weights."""
    step: Int[Array, ""]
    """Steps taken since init."""


class DoorInfo(NamedTuple):
    """Diagnostics of one step (stacked over time by :func:`filter`)."""

    mcl: MclInfo
    """ESS, resampled, mean pose, covariance, log-evidence increment, degenerate, ancestors."""
    door_belief: Float[Array, "K"]
    """sum_i w_i pi_i,k: the filter's marginal probability that door k is open (after the update,
    before resampling)."""
    door_observed: Float[Array, "K"]
    """Particle weight of the particles whose scan reached door k (0..1)."""
    door_beams: Float[Array, "K"]
    """Weighted mean number of beams attributed to door k."""


def init(state: mcl.MclState, door_map: DoorMap) -> DoorState:
    """A door filter state from an MCL particle set (``mcl.init_tracked`` / ``mcl.init_global``),
    every particle starting at the map's initial door beliefs."""
    n = state.poses.shape[0]
    door_open = jnp.broadcast_to(door_map.initial_open, (n, door_map.num_doors))
    return DoorState(state.poses, jnp.asarray(door_open, jnp.float32), state.log_weights, state.step)


class BeamAttribution(NamedTuple):
    """Which door each beam of a scan reaches first, and its expected ranges."""

    door: Int[Array, "B"]
    """Index k of the door the beam reaches before any wall, -1 for a wall (or nothing)."""
    range_closed: Float[Array, "B"]
    """Expected range (m) with every door closed: the first hit."""
    range_open: Float[Array, "B"]
    """Expected range (m) with the attributed door open (transparent), the other doors closed;
    equals ``range_closed`` for a beam attributed to no door."""


def attribute_beams(door_map: DoorMap, origin: Float[Array, "2"], angles: Float[Array, "B"],
                    range_max: Float[Array, ""]) -> BeamAttribution:
    """Beam-to-door attribution by two exact casts against the W + K segments (linear in K).

    The first cast, every door closed, gives each beam's first hit; a hit index >= W is door
    hit - W. The second makes only the hit segment transparent, per beam (an (B, M) active
    mask), giving the range behind an attributed door.
    """
    segments = all_segments(door_map)
    num_walls = door_map.num_walls
    range_closed, hit = raycast(segments, origin, angles, range_max)
    is_door = hit >= num_walls
    door = jnp.where(is_door, hit - num_walls, -1)
    # Per-beam mask: only the door that beam hit is open (walls are never made transparent).
    seg_index = jnp.arange(segments.shape[0])
    active = ~(is_door[:, None] & (seg_index[None, :] == hit[:, None]))  # (B, M)
    range_behind = jax.vmap(lambda a, act: raycast(segments, origin, a, range_max, act)[0])(angles, active)
    return BeamAttribution(door, range_closed, jnp.where(is_door, range_behind, range_closed))


class DoorLikelihoods(NamedTuple):
    """A scan's likelihood split into the static part and per-door parts (all tempered by the gain)."""

    static: Float[Array, ""]
    """log p(z_static | x): the beams that reach no door."""
    log_open: Float[Array, "K"]
    """log L_k(open): door k's beams scored with the door open (0 for a door no beam reaches)."""
    log_closed: Float[Array, "K"]
    """log L_k(closed): ... with the door closed."""
    num_beams: Float[Array, "K"]
    """Number of beams attributed to door k."""


def scan_door_likelihoods(door_map: DoorMap, pose: Float[Array, "3"], ranges: Float[Array, "B"],
                          sensor: SensorSpec, params: DoorParams, beam_stride: int = 1) -> DoorLikelihoods:
    """Split one scan's beam-model log-likelihood at ``pose`` into static and per-door parts."""
    lik_sensor, z = subsample_beams(sensor, ranges, beam_stride)
    origin, angles = laser_rays(pose, lik_sensor)
    att = attribute_beams(door_map, origin, angles, sensor.range_max)
    gain = params.likelihood_gain
    ll_closed = gain * beam_model_log_likelihood(att.range_closed, z, sensor.range_max, params.beam)
    ll_open = gain * beam_model_log_likelihood(att.range_open, z, sensor.range_max, params.beam)
    k = door_map.num_doors
    # Beams of no door go to a K-th bin, dropped: one segment-sum per quantity, O(B + K).
    bins = jnp.where(att.door >= 0, att.door, k)
    per_door = lambda v: jax.ops.segment_sum(v, bins, num_segments=k + 1)[:k]  # noqa: E731
    static = jnp.sum(jnp.where(att.door < 0, ll_closed, 0.0))
    return DoorLikelihoods(static, per_door(ll_open), per_door(ll_closed),
                           per_door(jnp.ones_like(ll_closed)))


def door_update(predicted_open: Float[Array, "K"], lik: DoorLikelihoods
                ) -> tuple[Float[Array, "K"], Float[Array, ""]]:
    """Eqs. 27-28 and 33 for one particle: ``(posterior p(open) per door, log weight increment)``.

    A door no beam reaches keeps its predicted belief and contributes nothing to the weight.
    """
    posterior, log_evidence = binary_bayes.update(predicted_open, lik.log_open, lik.log_closed)
    observed = lik.num_beams > 0
    posterior = jnp.where(observed, posterior, predicted_open)
    log_weight = lik.static + jnp.sum(jnp.where(observed, log_evidence, 0.0))
    return posterior, log_weight


def step(key: PRNGKeyArray, state: DoorState, inputs: ScanInputs, door_map: DoorMap, sensor: SensorSpec,
         params: DoorParams, config: DoorConfig) -> tuple[DoorState, DoorInfo]:
    """One step of the hybrid filter (or of the memoryless baseline, ``config.memory=False``).

    Args:
      key: PRNG key (split into motion and resampling keys, as :func:`jaxslam.localization.mcl.step`).
      state: poses (N, 3), door beliefs (N, K), log-weights (N,).
      inputs: odometry motion (3,) since the previous scan and the (B,) ranges (m).
      door_map: walls and doors.
      sensor: the laser.
      params: traced numbers (transition probabilities per door included).
      config: static settings.
    """
    k_motion, k_resample = jax.random.split(key)
    poses = motion_model.sample(k_motion, state.poses, inputs.motion, params.motion)
    if config.memory:
        predicted = binary_bayes.predict(state.door_open, params.p_open_open, params.p_open_closed)
    else:
        predicted = jnp.full_like(state.door_open, 0.5)
    lik = jax.vmap(lambda p: scan_door_likelihoods(door_map, p, inputs.ranges, sensor, params,
                                                   config.mcl.beam_stride))(poses)
    posterior, log_lik = jax.vmap(door_update)(predicted, lik)
    update = particle_filter.reweight_and_resample(k_resample, poses, state.log_weights, log_lik,
                                                   params.resample_threshold, config.mcl.resampler)
    w = jnp.exp(update.log_weights)  # after the update, before resampling (uniform when degenerate)
    door_info = DoorInfo(MclInfo.of(update), w @ posterior, w @ (lik.num_beams > 0).astype(jnp.float32),
                         w @ lik.num_beams)
    ancestors = update.ancestors
    new_state = DoorState(poses[ancestors], posterior[ancestors], update.new_log_weights, state.step + 1)
    return new_state, door_info


step_jit = jax.jit(step, static_argnames=("config",))
""":func:`step`, jitted (``config`` static)."""


def _filter(key, state, inputs, door_map, sensor, params, config) -> particle_filter.FilterOutput:
    return particle_filter.scan_filter(lambda k, s, inp: step(k, s, inp, door_map, sensor, params, config),
                                       key, state, inputs, lambda info: info.mcl.log_evidence)


filter = jax.jit(_filter, static_argnames=("config",))
"""``filter(key, state, inputs, door_map, sensor, params, config) -> FilterOutput(state, info,
marginal_loglik)``: the door filter over a whole log as one pure function, :func:`step` over
(T, ...) stacked ``inputs`` in one ``lax.scan`` (per-step keys split from ``key``), with the sum
of the steps' log-evidence. Jittable, vmappable, differentiable in ``params`` (the transition
probabilities included; each step rematerialised under reverse mode)."""


class DoorHistory(NamedTuple):
    """Per-step particle sets of one run (for figures): after each step's resampling."""

    poses: Float[Array, "T N 3"]
    door_open: Float[Array, "T N K"]
    log_weights: Float[Array, "T N"]


def _filter_history(key, state, inputs, door_map, sensor, params, config) -> particle_filter.FilterOutput:
    def step_keeping_particles(k, s, inp):
        new, info = step(k, s, inp, door_map, sensor, params, config)
        return new, (info, DoorHistory(new.poses, new.door_open, new.log_weights))

    return particle_filter.scan_filter(step_keeping_particles, key, state, inputs,
                                       lambda info: info[0].mcl.log_evidence, checkpoint=False)


filter_history = jax.jit(_filter_history, static_argnames=("config",))
"""As :func:`filter` (the same keys and steps), with every step's particles in the info:
``FilterOutput(state, (infos, DoorHistory), marginal_loglik)``, T N (K + 4) floats kept (for
figures). Its steps are not rematerialised under autodiff, so its values can differ from
:func:`filter`'s in the last bit (:func:`jaxslam.particle_filter.scan_filter`)."""
