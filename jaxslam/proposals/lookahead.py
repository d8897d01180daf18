"""The k-step look-ahead proposal (LP) of Grzonka, Plagemann, Grisetti and Burgard.

For one SLAM particle (pose x_{t-1}, map m = m_{t-1}) the LP runs a small particle
filter of L *localizer* particles k scans into the future in the fixed map m and uses
how well each time-t sample explains the future to choose the particle's new pose
(docs/design.md, "The look-ahead proposal"):

1. Draw x_t^(i) ~ p(x_t | x_{t-1}, u_t), i = 1..L; g_i = a_i = log p(z_t | x_t^(i), m);
   origin_i = i; log Z = 0. That is the paper's draw (``lookahead_initial="odometry"``); the
   default, ``"scan_match"``, draws them from the particle's window posterior
   (:mod:`jaxslam.window_posterior`: a mixture q of Gaussians round the modes of
   p(z_t | x, m)^gain p(x | x_{t-1}, u_t), every mode given a share) and sets g_i = log p(z_t | x_t^(i), m) + log p(x_t^(i) | x_{t-1}, u_t) - log q(x_t^(i)),
   an importance weight; steps 2-5 are the same for both.
2. For s = t+1 .. t+k: when the localizer ESS < ``resample_threshold`` * L,
   log Z += logsumexp(a) - log L and resample (poses, origin) by softmax(a), a = 0.
   Then move x_s ~ p(x_s | x_{s-1}, u_s) and a_i += log p(z_s | x_s^(i), m).
   Steps past the end of the log (``future_valid`` False) change nothing.
3. Back-propagate: log V_i = log Z + logsumexp_{m : origin_m = i} a_m (-inf when the
   time-t sample i has no descendant).
4. Select J with p_i = (1 - alpha) V_i / sum(V) + alpha exp(g_i) / sum(exp(g)).
5. log w_t = log w_{t-1} + g_J - log L - log p_J.

Step 5 is log mean_i exp(g_i) (the evidence estimate) plus the selection correction
log[softmax(g)_J / p_J], whose exponential has mean 1 over J. ``lookahead.selection_correction``
= c switches that correction: c = 1 is step 5; c = 0 keeps the evidence estimate alone, which is
unbiased for every alpha and does not depend on J, at the price of weighting poses that the
look-ahead chose (a smoothing-like draw) as if they came from the filter's proposal.

alpha = 0 is the paper's Eq. 10 (log w += log(sum(V) / L) + g_J - log V_J); it is
biased low because time-t samples whose line died out in the horizon's resampling
can never be drawn. Any alpha > 0 makes exp(increment) an unbiased estimate of
p(z_t | x_{t-1}, m, u_t): E_J[exp(g_J) / (L p_J)] = mean_i exp(g_i) whenever every
sample with g_i > -inf has p_i > 0, and alpha bounds the weight by
sum(exp(g)) / (L alpha).

Gains. :func:`propose` weighs the localizers with ``lookahead.localizer_gain`` (default
1: each scan's own likelihood, the sharpness the SMP fits with) and multiplies the increment
by ``likelihood.gain / localizer_gain``, so that the SLAM weights get the evidence tempered
to the filter's gain like every other proposal's. Tempering the localizers too (the gains
equal) flattens their weights until the selection barely prefers the poses that explain the
scans, and the LP drifts like the OP (the box-world figures: docs/design.md, "Gains", and
docs/results.md, "Box world").

Gradients (``jax.grad`` of the filter's log-likelihood; docs/design.md, "What a gradient of the
filter is"). The LP is an importance sampler on an extended space: the L time-t samples x, the
horizon's random numbers omega and J, drawn from Q = prod_i q(x_i) P(omega | x) p_J, weighted by
w = exp(g_J) / (L p_J). Q w = (1/L) gamma(x_J) prod_{i != J} q(x_i) P(omega | x), with gamma(x_J) =
exp(g_J) q(x_J), so E_Q[w f(x_J)] = integral of gamma f, and the score estimate of the gradient of
that integral is w d log gamma(x_J) = w (d g_J + d log q(x_J)) with every sample held fixed: the
score-function (REINFORCE) estimate, w (d log w + d log Q), less terms whose mean is 0 given x_J
(the other samples' scores, the horizon's). Each term, as computed:

* the time-t samples: drawn without pathwise gradient (``motion.sample_with_score``: the same
  pose as ``motion.sample`` for the same key), their score d log q(x_i) added to g_i as a term
  0 in value; with the scan-matched start the draw from the window posterior's mixture q carries
  no gradient and log q enters g without gradient (the draw's score and the weight's -d log q cancel);
* the draw of J: its score d log p_J cancels the -d log p_J of w exactly, so the increment is
  g_J - log L - stop_gradient(log p_J); in particular its derivative in alpha is 0 (alpha sets
  the variance, not the expectation: tests/test_lookahead.py checks both, and that the noise
  derivatives are the exact ones on a toy model);
* the horizon: it acts on the increment only through p_J, so it runs on stop-gradient samples and
  parameters (:func:`_propose_impl`), and reverse mode keeps none of its (K, L, beams)
  intermediates. Its moves and resamplings would add only scores of mean 0 given x_J (noise).
  :func:`run_horizon` itself keeps the resampling's score (w[a] / stop_gradient(w[a]), as
  ``resampling.resample_if_needed``) for a caller that differentiates its ``log_evidence``.

The values are unchanged: every term added is 0 and every stop-gradient the identity in value.
``selection_correction = 0`` (the increment log mean exp(g)) gets the gradient of that estimate,
every sample's score included. The gain ratio ``likelihood.gain / localizer_gain`` scales the
increment's gradient with its value; the estimate is that of p(z_t | ...) only at equal gains.

The model-independent core (:func:`run_horizon`, :func:`back_propagate`,
:func:`selection_log_probs`, :func:`select`, :func:`lookahead_core`) takes the
time-t samples, their log-likelihoods and two callables for the future steps, so it
can be tested on a toy model without grid maps. :func:`propose` plugs in the
odometry motion model and the endpoint likelihood; the RBPF vmaps it over SLAM
particles, and inside it everything is vectorised over the L localizers with a
``lax.scan`` over the horizon.
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jaxslam import motion, resampling
from jaxslam.proposals.base import Flag, ParamGroup, Proposal, ProposalOutput, Setting, StepInputs, step_params
from jaxslam.laser import SensorSpec
from jaxslam.map_view import MapView
from jaxslam.sensor_model import SensorModel, sensor_model
from jaxslam import window_posterior

# Fixed fold-in tags so that the random numbers of horizon step s do not depend on
# the horizon length K: a run whose last steps are invalid then equals a shorter run.
_TAG_INITIAL, _TAG_SELECT, _TAG_HORIZON = 0, 1, 2

LOCALIZER_UNIFORM_SHARE = 0.5
"""Share of the localizers drawn from the window posterior's modes uniformly, the rest by the
modes' masses: a mode lighter than the heaviest at time t still gets localizers, so the k
scans ahead can judge it (the point of looking ahead)."""

MoveFn = Callable[[PRNGKeyArray, Any, Any], Any]
"""``move(key, states, step_input) -> states``: propagate all L localizer states one step."""
LogLikelihoodFn = Callable[[Any, Any], Float[Array, "L"]]
"""``log_likelihood(states, step_input) -> (L,)``: log p(z_s | x_s^(i)) of every localizer."""


class HorizonResult(NamedTuple):
    """The localizer filter at the end of the horizon."""

    log_a: Float[Array, "L"]
    """Unnormalised log-weights a_m accumulated since the last resampling."""
    origin: Int[Array, "L"]
    """Index of the time-t sample each localizer descends from."""
    log_z: Float[Array, ""]
    """Sum over the resamplings of logsumexp(a) - log L (the evidence already paid out)."""
    states: Any
    """Final localizer states (for poses: (L, 3))."""
    num_resamplings: Int[Array, ""]
    """How many horizon steps resampled."""
    log_evidence: Float[Array, "K"]
    """After each step s: log Z + logsumexp(a) - log L, the filter's estimate of
    log p(z_{t:s} | x_{t-1}) (constant over steps past the end of the log)."""


class HorizonHistory(NamedTuple):
    """Per horizon step s = t+1..t+K, after moving and weighting (only with ``return_history``)."""

    states: Any
    """(K, L, ...) localizer states at step s."""
    log_a: Float[Array, "K L"]
    """Log-weights after step s."""
    origin: Int[Array, "K L"]
    """Time-t origin of each localizer at step s."""
    resampled: Bool[Array, "K"]
    """Whether step s resampled before moving."""
    valid: Bool[Array, "K"]
    """Whether step s was inside the log."""


class LookaheadDraw(NamedTuple):
    """The selection at time t."""

    index: Int[Array, ""]
    """J, the drawn time-t sample."""
    log_v: Float[Array, "L"]
    """log V_i, the back-propagated weights (-inf: no descendant)."""
    log_p: Float[Array, "L"]
    """log p_i, the selection probabilities (logsumexp = 0)."""
    log_weight_increment: Float[Array, ""]
    """log mean exp(g) + c (g_J - logsumexp(g) - log p_J), c the selection correction (c = 1:
    g_J - log L - log p_J; -inf when alpha = 0, c > 0 and every V is zero). The grid model
    (:func:`propose`, :func:`explain`) multiplies it by ``likelihood.gain / lookahead.localizer_gain``."""
    fallback: Bool[Array, ""]
    """Every V_i is zero: the draw used the defensive component alone."""


def run_horizon(
    key: PRNGKeyArray,
    states_t: Any,
    log_lik_t: Float[Array, "L"],
    future_inputs: Any,
    future_valid: Bool[Array, "K"],
    move: MoveFn,
    log_likelihood: LogLikelihoodFn,
    resample_threshold: Float[Array, ""],
    resample_fn: resampling.ResampleFn = resampling.systematic,
    return_history: bool = False,
) -> tuple[HorizonResult, HorizonHistory | None]:
    """Steps 1-2: run the L localizers through the horizon with ESS-triggered resampling.

    Args:
      key: randomness of the horizon (step s uses ``fold_in(key, s)``).
      states_t: the L time-t samples (a pytree with leading axis L; poses: (L, 3)).
      log_lik_t: (L,) g_i = log p(z_t | x_t^(i)).
      future_inputs: pytree with leading axis K, one entry per future step (motion, scan).
      future_valid: (K,) False for steps past the end of the log: they change nothing.
      move, log_likelihood: the model (see :data:`MoveFn`, :data:`LogLikelihoodFn`).
      resample_threshold: resample before step s when ESS(a) < this * L (> 1: always).
      resample_fn: a resampler of :mod:`jaxslam.resampling`.
      return_history: also return every step's cloud (static; for plots).

    After a resampling the weights are 1 (a = 0) in value, with the resampling's score term in
    their derivative (``w[a] / stop_gradient(w[a])``, as :func:`jaxslam.resampling.resample_if_needed`).
    :func:`lookahead_core` runs the horizon without gradient; this is for a direct caller.
    """
    num = log_lik_t.shape[0]
    log_num = math.log(num)
    origin0 = jnp.arange(num, dtype=jnp.int32)
    num_steps = future_valid.shape[0]

    def body(carry, xs):
        states, log_a, origin, log_z, count = carry
        step_index, step_input, valid = xs
        key_res, key_move = jax.random.split(jax.random.fold_in(key, step_index))
        do = valid & (resampling.ess(log_a) < resample_threshold * num)
        drawn = resample_fn(key_res, log_a, num)
        ancestors = jnp.where(do, drawn, origin0)
        total = jax.scipy.special.logsumexp(log_a)
        log_z = jnp.where(do, log_z + total - log_num, log_z)
        # After a resampling every weight is 1 (a = 0) in value; as in resampling.resample_if_needed
        # its derivative keeps the resampling's dependence on the parameters (a score term:
        # w[a] / stop_gradient(w[a]) of the normalised weights). A drawn localizer never has weight
        # zero; the where keeps an impossible -inf from making NaN.
        picked = log_a[drawn] - total
        score = jnp.where(jnp.isfinite(picked), picked - jax.lax.stop_gradient(picked), 0.0)
        log_a = jnp.where(do, score, log_a)
        origin = origin[ancestors]
        states = jax.tree.map(lambda s: s[ancestors], states)
        moved = move(key_move, states, step_input)
        new_log_a = log_a + log_likelihood(moved, step_input)
        states = jax.tree.map(lambda new, old: jnp.where(_expand(valid, new), new, old), moved, states)
        log_a = jnp.where(valid, new_log_a, log_a)
        count = count + do.astype(jnp.int32)
        log_evidence = log_z + _log_mean_exp(log_a)
        out = HorizonHistory(states, log_a, origin, do, valid) if return_history else None
        return (states, log_a, origin, log_z, count), (log_evidence, out)

    init = (states_t, log_lik_t, origin0, jnp.zeros((), log_lik_t.dtype), jnp.int32(0))
    xs = (jnp.arange(num_steps, dtype=jnp.int32), future_inputs, future_valid)
    (states, log_a, origin, log_z, count), (log_evidence, history) = jax.lax.scan(body, init, xs)
    return HorizonResult(log_a, origin, log_z, states, count, log_evidence), history


def _log_mean_exp(log_values: Float[Array, "L"]) -> Float[Array, ""]:
    """log mean_i exp(x_i): the evidence estimate of L weighted samples."""
    return jax.scipy.special.logsumexp(log_values) - math.log(log_values.shape[0])


def _expand(flag: Bool[Array, ""], like: Array) -> Bool[Array, "..."]:
    return jnp.reshape(flag, (1,) * like.ndim)


def back_propagate(
    log_a: Float[Array, "M"],
    origin: Int[Array, "M"],
    log_z: Float[Array, ""],
    num_origins: int | None = None,
) -> Float[Array, "L"]:
    """Step 3: log V_i = log Z + logsumexp over {m : origin_m = i} of a_m.

    Args:
      log_a: (M,) log-weights of the final localizers.
      origin: (M,) their time-t origins in 0..L-1.
      log_z: the evidence paid out by the horizon's resamplings.
      num_origins: L (default M).

    Returns:
      (L,) log V; -inf for a time-t sample without descendant. Never NaN.
    """
    num_origins = log_a.shape[0] if num_origins is None else num_origins
    # A dense (L, M) membership mask: L = M ~ 100 makes this a few thousand flops,
    # cheaper and simpler on CPU and GPU than a scatter-based segment logsumexp.
    member = origin[None, :] == jnp.arange(num_origins, dtype=origin.dtype)[:, None]
    # A sample without a descendant of nonzero weight has V = 0; its row is summed over zeros
    # instead (and set to -inf after) so that its derivative is 0, not logsumexp's NaN of an
    # all -inf row.
    alive = jnp.any(member & jnp.isfinite(log_a)[None, :], axis=1)
    rows = jnp.where(member, log_a[None, :], -jnp.inf)
    per_origin = jax.scipy.special.logsumexp(jnp.where(alive[:, None], rows, 0.0), axis=1)
    return log_z + jnp.where(alive, per_origin, -jnp.inf)


def selection_log_probs(
    log_v: Float[Array, "L"],
    log_lik_t: Float[Array, "L"],
    alpha: Float[Array, ""],
) -> tuple[Float[Array, "L"], Bool[Array, ""]]:
    """Step 4: log p_i = log[(1 - alpha) V_i / sum(V) + alpha exp(g_i) / sum(exp(g))].

    Both shares are normalised over this SLAM particle's L samples, so that p sums to 1
    and the increment does not depend on the overall scale of the future likelihoods.
    When every V_i is zero (``fallback``) the V share is undefined and p is the
    defensive share alone.
    """
    alpha = jnp.asarray(alpha, log_v.dtype)
    total_v = jax.scipy.special.logsumexp(log_v)
    fallback = ~jnp.isfinite(total_v)
    v_share = jnp.where(fallback, -jnp.inf, log_v - jnp.where(fallback, 0.0, total_v))
    g_share, _ = resampling.normalize_log_weights(log_lik_t)
    # Defensive share alone when every V is zero: alpha = 1 there.
    log_p = _log_mixture(jnp.where(fallback, 1.0, alpha), v_share, g_share)
    return log_p, fallback


def _mixture_log_weights(alpha):
    """(log(1 - alpha), log(alpha)), -inf at the ends without NaN in anything derived from them."""
    log_rest = jnp.where(alpha < 1.0, jnp.log1p(-jnp.where(alpha < 1.0, alpha, 0.0)), -jnp.inf)
    log_alpha = resampling.safe_log(alpha)
    return log_rest, log_alpha


@jax.custom_jvp
def _log_mixture(alpha, log_a, log_b):
    """log[(1 - alpha) exp(log_a) + alpha exp(log_b)] for alpha in [0, 1] and shares <= 0.

    The value is ``logaddexp(log1p(-alpha) + log_a, log(alpha) + log_b)``, with log(0) = -inf
    at alpha = 0 (the paper's form) and at alpha = 1. Its derivative is written out because
    autodiff of that expression is NaN at both ends (the derivative of log(alpha) is infinite
    at 0 and meets a zero from logaddexp); the mixture itself is smooth in alpha on [0, 1]."""
    log_rest, log_alpha = _mixture_log_weights(alpha)
    x, y = log_rest + log_a, log_alpha + log_b
    zero = jnp.isneginf(x) & jnp.isneginf(y)  # both components 0: log 0, without logaddexp's inner NaN
    return jnp.where(zero, -jnp.inf, jnp.logaddexp(jnp.where(zero, 0.0, x), jnp.where(zero, 0.0, y)))


@_log_mixture.defjvp
def _log_mixture_jvp(primals, tangents):
    alpha, log_a, log_b = primals
    d_alpha, d_a, d_b = tangents
    log_p = _log_mixture(alpha, log_a, log_b)
    ok = jnp.isfinite(log_p)
    safe_log_p = jnp.where(ok, log_p, 0.0)
    log_rest, log_alpha = _mixture_log_weights(alpha)

    def over_p(x, cap=jnp.inf):  # exp(x - log p), 0 where x or p is 0, at most exp(cap)
        fine = ok & jnp.isfinite(x)
        return jnp.where(fine, jnp.exp(jnp.minimum(jnp.where(fine, x, 0.0) - safe_log_p, cap)), 0.0)

    # The components' shares of p, (1 - alpha) a / p and alpha b / p, lie in [0, 1]; a / p and
    # b / p (the alpha derivative) are unbounded as p -> 0 and capped at exp(60) so that a
    # sample whose p is 0 to float32 gives 0 times a finite number, not 0 times inf (NaN).
    a_share, b_share = over_p(log_rest + log_a), over_p(log_alpha + log_b)
    d_log_p = ((over_p(log_b, 60.0) - over_p(log_a, 60.0)) * d_alpha
               + jnp.where(a_share > 0.0, a_share * d_a, 0.0) + jnp.where(b_share > 0.0, b_share * d_b, 0.0))
    return log_p, d_log_p


def select(
    key: PRNGKeyArray,
    log_v: Float[Array, "L"],
    log_lik_t: Float[Array, "L"],
    alpha: Float[Array, ""],
    selection_correction: Float[Array, ""] = 1.0,
) -> LookaheadDraw:
    """Steps 4-5: draw J ~ p and return the weight increment.

    ``selection_correction`` is 1 or 0: with 1 (default) the increment is g_J - log L - log p_J,
    with 0 the evidence estimate log mean exp(g) alone (without the selection correction
    g_J - logsumexp(g) - log p_J). With alpha = 0, correction 1 and every V zero the increment is
    -inf (the paper's weight is 0/0 there; the RBPF then drops the particle) and ``fallback``
    reports it. log p_J enters the increment without gradient: the score of the draw of J,
    d log p_J, cancels the importance ratio's -d log p_J (module docstring, "Gradients"), so the
    increment's derivative in alpha is 0 and the horizon's terms do not reach it.
    """
    num = log_v.shape[0]
    log_p, fallback = selection_log_probs(log_v, log_lik_t, alpha)
    index = jax.random.categorical(key, log_p).astype(jnp.int32)
    # The draw of J: its score d log p_J cancels the -d log p_J of the importance ratio exactly, so
    # p_J enters the increment without gradient (see the module docstring, "Gradients").
    full = log_lik_t[index] - math.log(num) - jax.lax.stop_gradient(log_p[index])
    corrected = jnp.asarray(selection_correction, log_lik_t.dtype) > 0.0
    increment = jnp.where(corrected, full, _log_mean_exp(log_lik_t))
    paper_form_undefined = fallback & (jnp.asarray(alpha) <= 0.0) & corrected
    increment = jnp.where(paper_form_undefined | jnp.isnan(increment), -jnp.inf, increment)
    return LookaheadDraw(index, log_v, log_p, increment, fallback)


def lookahead_core(
    key: PRNGKeyArray,
    states_t: Any,
    log_lik_t: Float[Array, "L"],
    future_inputs: Any,
    future_valid: Bool[Array, "K"],
    move: MoveFn,
    log_likelihood: LogLikelihoodFn,
    alpha: Float[Array, ""],
    resample_threshold: Float[Array, ""],
    resample_fn: resampling.ResampleFn = resampling.systematic,
    return_history: bool = False,
    selection_correction: Float[Array, ""] = 1.0,
) -> tuple[LookaheadDraw, HorizonResult, HorizonHistory | None]:
    """Steps 2-5 for given time-t samples (step 1 is the caller's: it owns the model).

    ``key`` is split by fold-in tags, never by the horizon length. See :func:`run_horizon`
    for the arguments and :func:`select` for ``selection_correction``. Returns the draw, the
    final horizon state and (optionally) history.

    Gradients (module docstring): ``log_lik_t`` should carry the time-t draws' score terms and
    ``states_t`` no pathwise gradient; the horizon runs on stop-gradient ``states_t`` and
    ``log_lik_t`` (p_J enters the increment without gradient, so nothing of it would reach the
    increment), and ``move`` and ``log_likelihood`` should close over stop-gradient parameters
    so that reverse mode stores nothing of the horizon.
    """
    # The horizon reaches the increment only through p_J, which enters it without gradient
    # (:func:`select`): it runs on stop-gradient samples, and ``move`` and ``log_likelihood``
    # should close over stop-gradient parameters (the grid model's do), so that reverse mode
    # keeps none of its (K, L, beams) intermediates.
    horizon, history = run_horizon(
        jax.random.fold_in(key, _TAG_HORIZON), jax.lax.stop_gradient(states_t), jax.lax.stop_gradient(log_lik_t),
        future_inputs, future_valid, move, log_likelihood, resample_threshold, resample_fn, return_history,
    )
    log_v = back_propagate(horizon.log_a, horizon.origin, horizon.log_z, log_lik_t.shape[0])
    draw = select(jax.random.fold_in(key, _TAG_SELECT), log_v, log_lik_t, alpha, selection_correction)
    return draw, horizon, history


# ---------------------------------------------------------------------------------------------
# The grid-map model.


def _grid_model(pose_params: motion.MotionParams, view: MapView, model: SensorModel, sensor, lik_params,
                lookup: str = "nearest"):
    def move(key, poses, step_input):
        step_motion, _ = step_input
        return motion.sample(key, poses, step_motion, pose_params)

    def log_likelihood(poses, step_input):
        _, ranges = step_input
        return model.log_likelihoods_fn(view, poses, ranges, sensor, lik_params, lookup)

    return move, log_likelihood


class LookaheadExplanation(NamedTuple):
    """Everything one LP draw computed, for plots (see ``notebooks/lookahead.ipynb``)."""

    poses_t: Float[Array, "L 3"]
    """The time-t samples x_t^(i)."""
    log_lik_t: Float[Array, "L"]
    """g_i."""
    draw: LookaheadDraw
    """J, log V, log p, the increment."""
    horizon: HorizonResult
    """The localizers at the end of the horizon."""
    history: HorizonHistory
    """The localizer cloud at every horizon step."""


def _propose_impl(key, pose, field, inputs: StepInputs, sensor, params, config, return_history, step_motion=None):
    spec = config.grid
    num = config.num_localizers
    # The localizer filter weighs with its own gain (default 1: the scan's own sharpness, as the
    # SMP's fit); the SLAM weight gets the evidence tempered to the filter's likelihood gain.
    localizer_gain = params.lookahead.localizer_gain
    evidence_scale = params.likelihood.gain / localizer_gain
    localizer_lik = params.likelihood._replace(gain=localizer_gain)
    view = MapView(spec, field)
    _, log_likelihood = _grid_model(params.motion, view, sensor_model(config), sensor, localizer_lik,
                                    config.likelihood_lookup)
    # The horizon's model, without gradient (see lookahead_core): the same values.
    no_grad = jax.lax.stop_gradient
    horizon_move, horizon_log_likelihood = _grid_model(
        no_grad(params.motion), jax.tree.map(no_grad, view), sensor_model(config), sensor, no_grad(localizer_lik),
        config.likelihood_lookup)
    start = jnp.broadcast_to(pose, (num, 3))
    key_initial = jax.random.fold_in(key, _TAG_INITIAL)
    # motion.sample's draw, with no pathwise gradient; its score (0 in value) goes into g_i.
    # Step t's motion model (the slip search's component, or params.motion); the horizon keeps params.motion.
    params_t = step_params(params, step_motion)
    poses_t, score_t = motion.sample_with_score(key_initial, start, inputs.motion, params_t.motion)
    log_lik_t = log_likelihood(poses_t, (inputs.motion, inputs.ranges)) + score_t
    if config.lookahead_initial == "scan_match":
        # Draw the time-t localizers from the window posterior's mixture instead (every mode gets
        # a share, LOCALIZER_UNIFORM_SHARE, whatever its mass: the horizon is what judges the
        # modes), and make g an importance weight:
        # g_i = log p(z_t | x_i) + log p(x_i | x_{t-1}, u_t) - log q(x_i). Steps 2-5 hold unchanged
        # for any proposal q with g so defined (the increment then estimates the same
        # p(z_t | x_{t-1}, m, u_t)). A failed match keeps the motion model.
        # q carries no gradient: the score of the draw, d log q(x_i), and the -d log q(x_i) of the
        # importance weight cancel (module docstring, "Gradients"), so neither the draw nor log q
        # needs one, and the search's discrete choices have none to give.
        posterior = jax.lax.stop_gradient(window_posterior.window_posterior(
            pose, field, inputs.motion, inputs.ranges, sensor, params_t, config, fit_gain=localizer_gain))
        log_mixture = window_posterior.mixture_log_weights(posterior, LOCALIZER_UNIFORM_SHARE)
        matched_t = window_posterior.sample(jax.random.fold_in(key_initial, 1), posterior, log_mixture, (num,))
        log_weight_t = window_posterior.importance_log_weights(
            matched_t, log_likelihood(matched_t, (inputs.motion, inputs.ranges)), pose, inputs.motion, params_t.motion,
            posterior, log_mixture)
        poses_t = jnp.where(posterior.matched, matched_t, poses_t)
        log_lik_t = jnp.where(posterior.matched, log_weight_t, log_lik_t)
    draw, horizon, history = lookahead_core(
        key, poses_t, log_lik_t, (inputs.future_motions, inputs.future_ranges), inputs.future_valid,
        horizon_move, horizon_log_likelihood, params.lookahead.alpha, params.lookahead.resample_threshold,
        resampling.RESAMPLERS[config.resampler], return_history, params.lookahead.selection_correction,
    )
    draw = draw._replace(log_weight_increment=evidence_scale * draw.log_weight_increment)
    return poses_t, log_lik_t, draw, horizon, history


def propose(
    key: PRNGKeyArray,
    pose: Float[Array, "3"],
    field,
    inputs: StepInputs,
    sensor: SensorSpec,
    params,
    config,
    step_motion=None,
) -> ProposalOutput:
    """One LP draw for one SLAM particle (see the module docstring); ``step_motion``: the motion
    model of step t's draw (None: ``params.motion``; the horizon's moves keep ``params.motion``).

    Uses ``config.num_localizers`` (L), the K = ``config.horizon`` future scans in
    ``inputs`` (invalid ones skipped), ``params.lookahead.alpha`` and
    ``params.lookahead.resample_threshold``; the map stays ``field`` (m_{t-1}'s likelihood field)
    over the whole horizon. ``fallback`` is True when no time-t sample kept weight.
    """
    poses_t, _, draw, _, _ = _propose_impl(key, pose, field, inputs, sensor, params, config, False,
                                                         step_motion)
    return ProposalOutput(poses_t[draw.index], draw.log_weight_increment, draw.fallback)


def explain(
    key: PRNGKeyArray,
    pose: Float[Array, "3"],
    field,
    inputs: StepInputs,
    sensor: SensorSpec,
    params,
    config,
    step_motion=None,
) -> LookaheadExplanation:
    """The same draw as :func:`propose` (same key and ``step_motion``, same result) with its
    intermediate quantities: the time-t samples, the horizon's clouds, V, p and J."""
    poses_t, log_lik_t, draw, horizon, history = _propose_impl(
        key, pose, field, inputs, sensor, params, config, True, step_motion)
    return LookaheadExplanation(poses_t, log_lik_t, draw, horizon, history)


class LookaheadParams(NamedTuple):
    """Traced numbers of the look-ahead proposal (``params.lookahead``)."""

    alpha: Float[Array, ""]
    """Defensive share in [0, 1): 0 is the paper's Eq. 10; > 0 makes the weights unbiased."""
    resample_threshold: Float[Array, ""]
    """Localizers are resampled inside the horizon when their ESS < this * L."""
    localizer_gain: Float[Array, ""]
    """Likelihood gain inside the localizer filter (its weights a, g and so the selection).
    1 uses each scan's own sharpness, as the SMP's fit does. The SLAM weight increment is
    then scaled by ``likelihood.gain / localizer_gain`` (the tempered evidence), so setting
    it equal to ``likelihood.gain`` tempers the localizers and leaves the increment as is."""
    selection_correction: Float[Array, ""]
    """Whether the SLAM weight keeps the selection correction: 1 or 0 (a switch, traced so that
    changing it never recompiles). 1 (default) is the design's increment g_J - log L - log p_J,
    unbiased for alpha > 0 but noisy, since it depends on which sample was drawn; 0 weighs every
    SLAM particle by its evidence estimate log mean_i exp(g_i) alone, unbiased for every alpha
    (the paper's 0 included) and independent of the draw, so the look-ahead then only chooses
    the pose."""


_SETTINGS = (
    Setting("num_localizers", 100, lambda v: v >= 1, ">= 1",
            "L, localizer particles per SLAM particle."),
    Setting("horizon", 5, lambda v: v >= 0, ">= 0",
            "k, the look-ahead horizon in processed scans (0: the LP's weights reduce to an average)."),
    Setting("lookahead_initial", "scan_match", lambda v: v in ("odometry", "scan_match"),
            "'odometry' or 'scan_match'",
            """Where the LP draws its L time-t localizers: "scan_match" (the default: a Gaussian fitted
    around each SLAM particle's scan-matched pose, importance-corrected; "LP-SM" in the docs) or
    "odometry" (the motion model, as in the paper). Along a featureless corridor the paper's
    localizers spread with the odometry and the particles inherit the spread; started from the
    match they stay pinned to the map (the figures:
    docs/results.md, "Ten seeds, four logs")."""),
)

_PARAMS = ParamGroup("lookahead", LookaheadParams,
                     {"alpha": 0.5, "resample_threshold": 0.5, "localizer_gain": 1.0, "selection_correction": 1.0},
                     {"alpha": (lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
                      # Above 1 is allowed (ESS <= L): the localizers are then resampled at every step.
                      "resample_threshold": (lambda v: v >= 0.0,
                                             ">= 0 (a fraction of L: 0 never resamples, above 1 always)"),
                      "localizer_gain": (lambda v: v > 0.0, "> 0"),
                      "selection_correction": (lambda v: v in (0.0, 1.0),
                                               "0 or 1 (keep the selection correction or not)")})


def _memory(config, num_beams: int) -> tuple[int, str]:
    """The localizers' beam terms: N x L x B float32 (B the beams used in likelihoods), twice."""
    beams = -(-num_beams // config.beam_stride)
    return (config.num_particles * config.num_localizers * beams * 4 * 2,
            f"{config.num_particles} x {config.num_localizers} localizers x {beams} beams x 4 bytes x 2")


PROPOSAL = Proposal(
    propose,
    "look-ahead: L localizers run k scans ahead in each particle's map (they start round the scan match; "
    "--set lookahead_initial=odometry: the paper's, from the motion model)",
    settings=_SETTINGS, params=_PARAMS,
    flags=(Flag("--localizers", "num_localizers", int, "localizer particles L per SLAM particle", minimum=1),
           Flag("--horizon", "horizon", int, "look-ahead horizon k, in processed scans", minimum=0),
           Flag("--alpha", "lookahead.alpha", float, "defensive share in [0, 1), 0 = the paper's Eq. 10")),
    future_scans_fn=lambda config: config.horizon,
    searches_window_fn=lambda config: config.lookahead_initial == "scan_match",
    memory_fn=_memory)
"""The LP's row of :data:`jaxslam.proposals.PROPOSALS`."""
