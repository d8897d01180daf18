"""The pose posterior over a window, searched coarse to fine with every mode kept.

For one SLAM particle (pose x_{t-1}, map m) and one step (odometry u_t, scan z_t), the
scan-matching proposal and the look-ahead's localizers draw from

    pi(x) = p(z_t | x, m)^gain p(x | x_{t-1}, u_t),

the motion prior inside. The search runs in the motion model's own coordinates: a candidate is
the offset delta in x = x_{t-1} (+) (u_t + delta), so the prior is the Gaussian
N(delta; 0, diag(std^2)) of :func:`jaxslam.motion.noise_std`, separable per axis, and the window
is the box |delta_k| <= max(``scan_match.window_sigmas`` std_k, floor_k).

1. **Coarse level.** The window is cut into ``window_cells``^3 cells (static), each scored by
   the sensor model's cell likelihood (:func:`jaxslam.likelihood_field.endpoint_cell_log_likelihoods`:
   the centre's, each beam widened by how far the cell moves its endpoint) times the gain, plus
   the prior at the point of the cell closest to delta = 0. The cells that are local maxima of
   that score among their 26 neighbours come first; the best ``window_modes`` (static) of them seed
   the modes, so a second hypothesis one cell away from the first cannot crowd out one across
   the window.
2. **Finer levels** (``window_levels``, static). Each mode splits its ``window_keep`` cells into
   their 8 halves, scores them (the cell score again; the last level the likelihood itself at
   the cells' centres, with ``likelihood_lookup``, the weights' own) and keeps its best
   ``window_keep``. Within a mode the likelihood has the gain ``fit_gain`` (the scan's own
   sharpness decides where in a mode the pose lies; the tempered posterior decides which modes
   there are and what each weighs). Modes never compete for places, so every mode is refined to
   the last level. Every candidate of every mode (and under the filter's vmap, of every
   particle) is one batched evaluation: the step's sequential depth is the number of levels
   plus the polish and the fit, where the hill climber it replaced had 24 dependent rounds.
3. **Polish.** Each mode's best cell and its 8 halves, read with ``match_lookup`` (bilinear by
   default: continuous in the pose, so the peak settles between the field's cells); the best
   of the nine is the mode's peak.
4. **Fit.** Round each mode's best pose a 3 x 3 x 3 stencil (spacing
   ``scan_match.linear_step``, ``angular_step``): the likelihood at ``fit_gain`` (the SMP: 1,
   the scan's own sharpness, as GMapping) on it gives a Gaussian (its weights' moments), and the
   mode's Gaussian is that times the motion prior, which is exactly Gaussian in world
   coordinates (:func:`jaxslam.motion.world_gaussian`): a product in closed form. Inside the
   stencil's weights a prior narrower than the spacing (the box world's: 0.013 m along the
   track against 5 cm) would leave the centre alone and collapse the fit to its floor, a
   proposal narrower than the prior where the scan says nothing. The mode's mass is the
   stencil's Riemann sum of pi (at the filter's gain, with the prior). A mode whose stencil
   overlaps a heavier mode's (its best pose within two stencil spacings on every axis) is the
   same hypothesis found twice, and is dropped.

The proposal is the mixture of the modes' Gaussians with weights proportional to their masses
(:func:`sample`, :func:`log_density`); its weight increment is the log of the summed masses,
the quadrature of p(z_t | x_{t-1}, m, u_t) = int pi(x) dx over the kept modes' stencils. What
the pruning leaves out (the mass of cells never refined) is missing from it: docs/design.md
gives the measured size of that.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from jaxslam import motion
from jaxslam.geometry import compose, wrap_angle
from jaxslam.laser import within_usable_range
from jaxslam.map_view import MapView
from jaxslam.motion import LOG_2PI
from jaxslam.sensor_model import SensorModel, sensor_model

# NumPy, not jnp: module-level jnp values created while a trace is active would leak tracers.
_STENCIL = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.float32)  # (27, 3)
_HALVES = np.array(list(itertools.product((-0.25, 0.25), repeat=3)), dtype=np.float32)  # (8, 3) of a cell's side


class WindowPosterior(NamedTuple):
    """One particle's window posterior: M modes (M = ``config.window_modes``), each a Gaussian
    over the new pose x_t in world coordinates (m, m, rad)."""

    means: Float[Array, "M 3"]
    """Mean pose of each mode's Gaussian."""
    chols: Float[Array, "M 3 3"]
    """Lower Cholesky factor of each mode's covariance."""
    log_masses: Float[Array, "M"]
    """log of each mode's mass of pi (its stencil's Riemann sum); -inf for a mode dropped as a
    duplicate of a heavier one."""
    peaks: Float[Array, "M 3"]
    """Each mode's best pose found by the search."""
    log_eta: Float[Array, ""]
    """logsumexp of ``log_masses``: the SMP's weight increment, the quadrature of
    p(z_t | x_{t-1}, m, u_t)."""
    matched: Bool[Array, ""]
    """The heaviest mode's match score is at least ``scan_match.min_score`` and the mass finite."""


def half_widths(motion_step: Float[Array, "3"], params) -> Float[Array, "3"]:
    """Half-sides (m, m, rad) of the window in the motion model's offsets: ``window_sigmas`` times
    the step's noise stds, at least ``window_min_xy`` and ``window_min_theta``."""
    sm = params.scan_match
    floors = jnp.stack([sm.window_min_xy, sm.window_min_xy, sm.window_min_theta])
    return jnp.maximum(sm.window_sigmas * motion.noise_std(motion_step, params.motion), floors)


def _log_prior(offsets: Float[Array, "... 3"], std: Float[Array, "3"]) -> Float[Array, "..."]:
    """log N(offsets; 0, diag(std^2)): the motion model's density of x_{t-1} (+) (u + offset)."""
    return jnp.sum(-0.5 * (offsets / std) ** 2 - jnp.log(std) - 0.5 * LOG_2PI, axis=-1)


def coarse_offsets(half: Float[Array, "3"], cells: int) -> Float[Array, "C 3"]:
    """The centres of the coarse cells, ``cells``^3 of them (static), in (x, y, theta) order."""
    axis = (np.arange(cells, dtype=np.float32) + 0.5) / cells * 2.0 - 1.0
    unit = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    return jnp.asarray(unit) * half


def _local_maxima_first(scores: Float[Array, "C"], cells: int) -> Float[Array, "C"]:
    """``scores`` with every cell that is not a maximum among its 26 neighbours moved below all
    that are, in order (for picking the modes' seeds: every separate peak first, then the best
    of the rest, which near a broad peak are its neighbours)."""
    finite = jnp.where(jnp.isfinite(scores), scores, jnp.nan)
    low, high = jnp.nanmin(finite), jnp.nanmax(finite)
    finite = jnp.where(jnp.isfinite(scores), scores, low - 1.0)
    cube = finite.reshape(cells, cells, cells)
    neighbours = jax.lax.reduce_window(cube, -jnp.inf, jax.lax.max, (3, 3, 3), (1, 1, 1), "SAME")
    is_max = (cube >= neighbours).reshape(-1)
    # Shifted by the scores' range (not by a huge constant, which would round them all alike).
    return jnp.where(is_max, finite, finite - (high - low) - 2.0)


def _polish(mode_cells: Float[Array, "M K 3"], spacing: Float[Array, "3"], exact, config) -> Float[Array, "M 3"]:
    """Each mode's best cell (``mode_cells[:, 0]``: top_k sorts) and its 8 halves, scored by
    ``exact(offsets, lookup)`` with ``config.match_lookup`` (bilinear: the posterior is continuous
    in the pose there, so the peak settles between cells); the best of the nine offsets per mode."""
    best_cell = mode_cells[:, 0, :]
    polish = jnp.concatenate([best_cell[:, None, :], best_cell[:, None, :] + jnp.asarray(_HALVES) * spacing], axis=1)
    polish_scores = exact(polish.reshape(-1, 3), config.match_lookup).reshape(config.window_modes, -1)
    polish_scores = jnp.where(jnp.isnan(polish_scores), -jnp.inf, polish_scores)
    return jnp.take_along_axis(polish, jnp.argmax(polish_scores, axis=1)[:, None, None], axis=1)[:, 0]


def window_posterior(pose: Float[Array, "3"], field, motion_step: Float[Array, "3"], ranges: Float[Array, "B"],
                     sensor, params, config, fit_gain) -> WindowPosterior:
    """The window posterior of one particle (see the module docstring).

    Args:
      pose: x_{t-1} (m, m, rad).
      field: the particle's likelihood field (a paged map's ``PagedField``, or a dense (H, W)
        field where ``config.grid`` is a dense ``GridSpec``).
      motion_step: u_t, the odometry motion [dx, dy, dtheta] in x_{t-1}'s frame.
      ranges: (B,) the scan z_t (beam-subsampled to match ``sensor``).
      sensor: the laser.
      params: ``SlamParams``: the likelihood, the motion noise and the scan matcher's numbers.
      config: ``SlamConfig``: ``window_cells``, ``window_levels``, ``window_modes``,
        ``window_keep``, ``likelihood_lookup``, ``field_radius`` and ``max_insert_range`` (static).
      fit_gain: the likelihood gain of the modes' Gaussians (the SMP: 1).
    """
    model = sensor_model(config)
    view = MapView(config.grid, field)
    sm = params.scan_match
    gain = params.likelihood.gain
    untempered = params.likelihood._replace(gain=jnp.float32(1.0))
    std = motion.noise_std(motion_step, params.motion)
    half = half_widths(motion_step, params)
    cells = config.window_cells

    def poses_at(offsets):
        return compose(pose, motion_step + offsets)

    def cell_score(offsets, spacing, sharpness):
        """log pi of the cells of side ``spacing`` centred on ``offsets``, the likelihood at gain
        ``sharpness``: the cell likelihood and the prior's largest value in the cell."""
        closest = jnp.clip(0.0, offsets - 0.5 * spacing, offsets + 0.5 * spacing)
        if model.cell_log_likelihoods_fn is None:
            log_lik = model.log_likelihoods_fn(view, poses_at(offsets), ranges, sensor, untempered, "nearest")
        else:
            log_lik = model.cell_log_likelihoods_fn(view, poses_at(offsets), ranges, sensor, untempered,
                                                     0.5 * jnp.hypot(spacing[0], spacing[1]), 0.5 * spacing[2],
                                                     config.field_radius)
        return sharpness * log_lik + _log_prior(closest, std)

    def exact(offsets, lookup):
        log_lik = model.log_likelihoods_fn(view, poses_at(offsets), ranges, sensor, untempered, lookup)
        return fit_gain * log_lik + _log_prior(offsets, std)

    # 1. The coarse level: the modes' seeds.
    spacing = 2.0 * half / cells
    offsets = coarse_offsets(half, cells)
    scores = cell_score(offsets, spacing, gain)
    _, seeds = jax.lax.top_k(_local_maxima_first(scores, cells), config.window_modes)
    mode_cells = offsets[seeds][:, None, :]  # (M, 1, 3)
    # 2. The finer levels, each mode on its own.
    for level in range(config.window_levels):
        children = (mode_cells[:, :, None, :] + jnp.asarray(_HALVES) * spacing).reshape(config.window_modes, -1, 3)
        spacing = 0.5 * spacing
        flat = children.reshape(-1, 3)
        last = level == config.window_levels - 1
        child_scores = (exact(flat, config.likelihood_lookup) if last
                        else cell_score(flat, spacing, fit_gain)).reshape(config.window_modes, -1)
        child_scores = jnp.where(jnp.isnan(child_scores), -jnp.inf, child_scores)
        keep = min(config.window_keep, children.shape[1])
        _, best = jax.lax.top_k(child_scores, keep)
        mode_cells = jnp.take_along_axis(children, best[..., None], axis=1)
    # 3. The polish of each mode's best cell.
    peaks = poses_at(_polish(mode_cells, spacing, exact, config))
    # 4. A Gaussian and a mass per mode, from the stencil round its peak.
    gaussians = jax.vmap(lambda peak: _fit_mode(peak, pose, view, model, motion_step, ranges, sensor, params,
                                                config, fit_gain))(peaks)
    means, chols, log_masses = gaussians
    log_masses = _drop_duplicates(peaks, log_masses, sm)
    log_eta = jax.scipy.special.logsumexp(log_masses)
    heaviest = jnp.argmax(log_masses)
    # The score counts only the beams the map can know (SlamConfig.max_insert_range).
    scored = within_usable_range(ranges, config.max_insert_range)
    score = model.match_score_fn(view, peaks[heaviest], scored, sensor, params.likelihood)
    matched = (score >= sm.min_score) & jnp.isfinite(log_eta)
    return WindowPosterior(means, chols, log_masses, peaks, log_eta, matched)


def stencil_poses(center: Float[Array, "3"], scan_match_params) -> tuple[Float[Array, "27 3"], Float[Array, "27 3"],
                                                                         Float[Array, "3"]]:
    """The 3x3x3 stencil round a pose, spaced by ``scan_match.linear_step`` and ``angular_step``.

    Returns:
      ``(poses, offsets, spacing)``: (27, 3) poses (angles wrapped), their (27, 3) offsets
      from ``center`` and the (3,) spacing (m, m, rad).
    """
    sm = scan_match_params
    spacing = jnp.stack([sm.linear_step, sm.linear_step, sm.angular_step])
    offsets = _STENCIL * spacing
    poses = center + offsets
    return poses.at[:, 2].set(wrap_angle(poses[:, 2])), offsets, spacing


def _fit_mode(peak, pose, view, model: SensorModel, motion_step, ranges, sensor, params, config, fit_gain):
    """One mode's Gaussian and log-mass from the stencil round its peak: the Gaussian is the
    likelihood's (at ``fit_gain``: its stencil weights' moments plus the floor) times the motion
    prior's (in closed form, the Kalman update of the one by the other); the log-mass the
    stencil's Riemann sum of the likelihood at the filter's gain times the prior."""
    sm = params.scan_match
    candidates, offsets, spacing = stencil_poses(peak, sm)
    untempered = params.likelihood._replace(gain=jnp.float32(1.0))
    raw_log_lik = model.log_likelihoods_fn(view, candidates, ranges, sensor, untempered, config.likelihood_lookup)
    log_prior = motion.log_density(candidates, pose, motion_step, params.motion)
    log_mass = (jax.scipy.special.logsumexp(params.likelihood.gain * raw_log_lik + log_prior)
                + jnp.sum(jnp.log(spacing)))
    # The likelihood's Gaussian from the stencil, then its product with the prior's in closed
    # form: a prior narrower than the spacing, inside the weights, would collapse the fit.
    weights = jax.nn.softmax(fit_gain * raw_log_lik)
    mean_offset = weights @ offsets
    centred = offsets - mean_offset
    cov_lik = (centred * weights[:, None]).T @ centred + jnp.diag((sm.min_std_fraction * spacing) ** 2)
    lik_mean = peak + mean_offset
    prior_mean, cov_prior = motion.world_gaussian(pose, motion_step, params.motion)
    residual = prior_mean - lik_mean
    residual = residual.at[2].set(wrap_angle(residual[2]))
    gain_matrix = jnp.linalg.solve(cov_lik + cov_prior, cov_lik).T  # cov_lik (cov_lik + cov_prior)^-1
    mean = lik_mean + gain_matrix @ residual
    cov = cov_lik - gain_matrix @ cov_lik
    cov = 0.5 * (cov + cov.T)
    mean = mean.at[2].set(wrap_angle(mean[2]))
    log_mass = jnp.where(jnp.isnan(log_mass), -jnp.inf, log_mass)
    return mean, jnp.linalg.cholesky(cov), log_mass


def _drop_duplicates(peaks: Float[Array, "M 3"], log_masses: Float[Array, "M"], scan_match_params
                     ) -> Float[Array, "M"]:
    """``log_masses`` with -inf for every mode whose stencil overlaps a heavier mode's (its peak
    within two stencil spacings on every axis; ties: the earlier mode is the heavier): the same
    hypothesis found twice, whose mass the sum would otherwise count twice."""
    sm = scan_match_params
    spacing = jnp.stack([sm.linear_step, sm.linear_step, sm.angular_step])
    gap = jnp.abs(peaks[:, None, :] - peaks[None, :, :])
    gap = gap.at[..., 2].set(jnp.abs(wrap_angle(gap[..., 2])))
    same = jnp.all(gap < 2.0 * spacing, axis=-1)  # (M, M): the two stencils overlap
    order = jnp.arange(peaks.shape[0])
    heavier = (log_masses[None, :] > log_masses[:, None]) | (
        (log_masses[None, :] == log_masses[:, None]) & (order[None, :] < order[:, None]))
    duplicate = jnp.any(same & heavier & ~jnp.eye(peaks.shape[0], dtype=bool), axis=-1)
    return jnp.where(duplicate, -jnp.inf, log_masses)


def mixture_log_weights(posterior: WindowPosterior, uniform_share=0.0) -> Float[Array, "M"]:
    """log of the mixture's weights: the modes' masses normalised, mixed with ``uniform_share``
    of a uniform choice among the kept modes (the look-ahead's localizers: every mode gets some,
    whatever its mass; the importance weights correct for it)."""
    kept = jnp.isfinite(posterior.log_masses)
    by_mass = jax.nn.log_softmax(jnp.where(kept, posterior.log_masses, -jnp.inf))
    num_kept = jnp.maximum(jnp.sum(kept), 1)
    uniform = jnp.where(kept, -jnp.log(num_kept.astype(by_mass.dtype)), -jnp.inf)
    share = jnp.asarray(uniform_share, by_mass.dtype)
    return jnp.logaddexp(jnp.log1p(-share) + by_mass, jnp.log(share) + uniform)


def sample(key: PRNGKeyArray, posterior: WindowPosterior, log_mixture: Float[Array, "M"],
           shape: tuple[int, ...] = ()) -> Float[Array, "... 3"]:
    """Draws from the mixture of the modes' Gaussians with log-weights ``log_mixture`` (a mode,
    then a pose from its Gaussian; angles wrapped)."""
    key_mode, key_pose = jax.random.split(key)
    modes = jax.random.categorical(key_mode, log_mixture, shape=shape)
    noise = jax.random.normal(key_pose, shape + (3,), posterior.means.dtype)
    draw = posterior.means[modes] + jnp.einsum("...ij,...j->...i", posterior.chols[modes], noise)
    return draw.at[..., 2].set(wrap_angle(draw[..., 2]))


def log_density(poses: Float[Array, "... 3"], posterior: WindowPosterior, log_mixture: Float[Array, "M"]
                ) -> Float[Array, "..."]:
    """log of the mixture's density at ``poses`` (m^-2 rad^-1; angle residuals wrapped)."""
    residual = poses[..., None, :] - posterior.means  # (..., M, 3)
    residual = residual.at[..., 2].set(wrap_angle(residual[..., 2]))
    chols = jnp.broadcast_to(posterior.chols, residual.shape + (3,))
    z = jax.scipy.linalg.solve_triangular(chols, residual[..., None], lower=True)[..., 0]
    log_det = jnp.sum(jnp.log(jnp.diagonal(posterior.chols, axis1=-2, axis2=-1)), axis=-1)
    per_mode = -0.5 * jnp.sum(z**2, axis=-1) - log_det - 1.5 * LOG_2PI
    return jax.scipy.special.logsumexp(log_mixture + per_mode, axis=-1)


def importance_log_weights(poses: Float[Array, "... 3"], log_likelihoods: Float[Array, "..."], pose: Float[Array, "3"],
                           motion_step: Float[Array, "3"], motion_params, posterior: WindowPosterior,
                           log_mixture: Float[Array, "M"]) -> Float[Array, "..."]:
    """log gamma(x) - log q(x) at ``poses`` drawn from the mixture (:func:`sample`): gamma the
    target, ``log_likelihoods`` (the scan's, tempered as the caller weighs) times the motion prior
    p(x | ``pose``, ``motion_step``), q the mixture. With the posterior and the poses carrying no
    gradient, its gradient is d log gamma, the drawn poses' score (the SMP's "importance" weight,
    the LP's scan-matched localizers)."""
    return (log_likelihoods + motion.log_density(poses, pose, motion_step, motion_params)
            - log_density(poses, posterior, log_mixture))
