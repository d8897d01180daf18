"""Fitting a filter's parameters to data: Adam on the log-likelihood, in plain JAX.

The filters return an estimate of log p(data | params) whose gradient is the score estimate
(:func:`jaxslam.resampling.resample_if_needed`): :func:`fit` climbs it with Adam (Kingma &
Ba 2015; written here, the design card has no optax) over *unconstrained* coordinates, so
that a noise stays positive (log) and a probability inside (0, 1) (logit). Parameters are
addressed by their dotted names (``"motion.srr"``, as ``--set`` and ``default_params`` do);
any of them can be frozen. The optimiser is a ``NamedTuple(init, step)`` of pure functions,
as in optax and blackjax.

The gradient of ``rbpf.filter``'s estimate is the path-space score by default;
``SlamConfig.score_lag`` makes it the fixed-lag smoothed score
(:func:`jaxslam.particle_filter.fixed_lag_score`: the same bias, less spread on a
linear-Gaussian model; no change where the weights collapse every step, as on the simulated
office: docs/design.md, "What a gradient of the filter is").

Learn with the SMP (:func:`slam_learning_setup` sets its importance weight): it draws from the
window posterior, so far fewer of its draws lose their weight in a step than the OP's, and a
fit from twice the truth on the simulated office ends with every motion term within 10 % of the
known path's optimum (sigma at 1.16x) at 50 particles, where the OP's ends at 0.65x in srt with 200
(docs/design.md, "What a gradient of the filter is").

Fit with the untempered likelihood (``likelihood.gain`` 1 for the RBPF, ``likelihood_gain`` 1
for MCL and the doors) and leave the gain out of ``trainable``: a gain below 1 makes the
objective a tempered pseudo-likelihood whose maximum is not at the true noise
(docs/design.md, "Tempering and learning").

    from jaxslam.learning import fit
    result = fit(jax.random.key(0), lambda key, p: rbpf.filter(key, prepared, p, config).marginal_loglik,
                 params, num_steps=50, learning_rate=0.05, trainable=["motion.srr", "likelihood.sigma"])
    result.params, result.history["objective"]
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Literal
from jaxtyping import Array, Float, Int, PRNGKeyArray
from tqdm.auto import tqdm

from jaxslam.config import build_setup
from jaxslam.warn import warn


class Transform(NamedTuple):
    """A bijection between an unconstrained real and a parameter's domain."""

    to_constrained_fn: Callable[[Array], Array]
    to_unconstrained_fn: Callable[[Array], Array]
    domain: str
    """What the parameter's value must be, for error messages."""
    contains_fn: Callable[[float], bool]


POSITIVE = Transform(jnp.exp, jnp.log, "> 0", lambda v: v > 0.0)
"""Noise, sigma, gains: log / exp."""
UNIT_INTERVAL = Transform(jax.nn.sigmoid, lambda p: jnp.log(p) - jnp.log1p(-p), "in (0, 1)", lambda v: 0.0 < v < 1.0)
"""Probabilities and shares: logit / sigmoid."""
REAL = Transform(lambda x: x, lambda x: x, "finite", lambda v: bool(np.isfinite(v)))
"""Any real (log-odds, offsets)."""


class AdamState(NamedTuple):
    """Adam's moments of every trained coordinate."""

    step: Int[Array, ""]
    """Updates done."""
    mean: Any
    """First-moment estimate (the coordinates' pytree)."""
    second_moment: Any
    """Second-moment estimate."""


class Optimizer(NamedTuple):
    """``init(coords) -> state`` and ``step(state, coords, grads) -> (coords, state)``."""

    init: Callable[[Any], AdamState]
    step: Callable[[AdamState, Any, Any], tuple[Any, AdamState]]


def adam(learning_rate: float, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8) -> Optimizer:
    """Adam for *ascent*: ``step`` moves the coordinates along ``grads`` (of an objective to maximise)."""

    def init(coords) -> AdamState:
        zeros = jax.tree.map(jnp.zeros_like, coords)
        return AdamState(jnp.int32(0), zeros, zeros)

    def step(state: AdamState, coords, grads):
        t = state.step + 1
        mean = jax.tree.map(lambda m, g: b1 * m + (1.0 - b1) * g, state.mean, grads)
        second = jax.tree.map(lambda v, g: b2 * v + (1.0 - b2) * g * g, state.second_moment, grads)
        correction1, correction2 = 1.0 - b1 ** t, 1.0 - b2 ** t
        coords = jax.tree.map(
            lambda x, m, v: x + learning_rate * (m / correction1) / (jnp.sqrt(v / correction2) + eps),
            coords, mean, second)
        return coords, AdamState(t, mean, second)

    return Optimizer(init, step)


def param_names(params) -> list[str]:
    """Dotted names of a parameter pytree's leaves (``"motion.srr"``), in leaf order."""
    return [jax.tree_util.keystr(path, simple=True, separator=".")
            for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]]


class FitResult(NamedTuple):
    """What :func:`fit` returns."""

    params: Any
    """The parameters after the last step (the input's pytree type)."""
    history: dict[str, np.ndarray]
    """``"objective"``: (num_steps,) the objective at each step's parameters (before its
    update); one (num_steps,) array per trained name: its value at that step."""
    optimizer_state: AdamState
    """Pass back as ``initial_state`` (with ``params``) to continue where this fit stopped."""


def fit(
    key: PRNGKeyArray,
    objective_fn: Callable[[PRNGKeyArray, Any], Float[Array, ""]],
    params,
    *,
    num_steps: int,
    learning_rate: float = 0.05,
    trainable: Sequence[str] | None = None,
    transforms: dict[str, Transform] | None = None,
    initial_state: AdamState | None = None,
    progress: bool = True,
    check_gradients: bool = True,
) -> FitResult:
    """Maximise ``objective_fn(key, params)`` (a log-likelihood estimate) with Adam.

    Each step draws a new key, evaluates the objective and its gradient in one jitted call
    (compiled once) and updates the trained parameters in their unconstrained coordinates.

    Args:
      key: the fit's key (split into one key per step).
      objective_fn: ``(key, params) -> scalar`` to maximise, differentiable in ``params``.
      params: the starting parameters (any pytree of scalar arrays: ``SlamParams``,
        ``MclParams``, ``DoorParams``...).
      num_steps: updates to make (>= 1).
      learning_rate: Adam's step in unconstrained coordinates (0.05: about 5 % of a positive
        parameter per step at most).
      trainable: dotted names to fit (default every leaf); the others stay frozen.
      transforms: name -> :data:`POSITIVE`, :data:`UNIT_INTERVAL` or :data:`REAL`; a name not
        given is POSITIVE.
      initial_state: an earlier fit's ``optimizer_state`` to resume it.
      progress: show a tqdm bar with the objective.
      check_gradients: refuse trainable names whose gradient is zero by construction
        (:func:`structurally_zero`; costs one trace of the gradient).

    Raises:
      ValueError: before any work, for an unknown trainable name, a starting value outside its
        transform's domain (a zero noise under log), a trainable name the objective's gradient
        cannot reach (``check_gradients``), or ``num_steps < 1``.
      FitError: at the first step whose objective or gradient is not finite (a filter's step
        that lost every particle, or whose map pools overflowed: ``rbpf.filter``), naming the
        parameters whose gradient is not; its ``result`` is the fit up to the step before.
    """
    if isinstance(num_steps, bool) or not isinstance(num_steps, (int, np.integer)) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")
    trainable, transforms, to_params, coords = _unconstrained_start(params, trainable, transforms)
    if check_gradients:
        dead = structurally_zero(lambda c: objective_fn(key, to_params(c)), coords)
        if dead:
            raise ValueError(f"the objective's gradient is zero by construction in {dead}: nothing can be learned "
                             f"for them (they act through comparisons or a non-differentiable step, such as the "
                             f"map insertion or a resampling threshold); leave them out of trainable")
    optimizer = adam(learning_rate)
    state = optimizer.init(coords) if initial_state is None else initial_state

    @jax.jit
    def update(step_key, coords, state):
        value, grads = jax.value_and_grad(lambda c: objective_fn(step_key, to_params(c)))(coords)
        new_coords, new_state = optimizer.step(state, coords, grads)
        return value, {name: jnp.isfinite(g) for name, g in grads.items()}, new_coords, new_state

    return _run_fit(key, num_steps, update, to_params, coords, state, trainable, transforms, progress)


def _unconstrained_start(params, trainable: Sequence[str] | None, transforms: dict[str, Transform] | None):
    """Check :func:`fit`'s names and starting values and set up its unconstrained coordinates.

    Returns:
      ``(trainable, transforms, to_params, coords)``: the trained names (a list); each one's
      :class:`Transform` (POSITIVE where none was given); ``to_params(coords)``, the parameters
      (``params``' pytree, frozen leaves as given) at unconstrained coordinates ``coords``; and
      the starting ``coords``, name -> float32 scalar.

    Raises:
      ValueError: an unknown name, or a starting value outside its transform's domain.
    """
    names = param_names(params)
    leaves, treedef = jax.tree.flatten(params)
    trainable = list(names) if trainable is None else list(trainable)
    unknown = sorted(set(trainable) - set(names)) + sorted(set(transforms or {}) - set(names))
    if unknown:
        raise ValueError(f"unknown parameter names {unknown}; the parameters are {names}")
    transforms = {name: (transforms or {}).get(name, POSITIVE) for name in trainable}
    for name in trainable:
        value = float(np.asarray(leaves[names.index(name)]))
        if not transforms[name].contains_fn(value):
            raise ValueError(f"{name} = {value} is outside its transform's domain ({transforms[name].domain}): "
                             "start it inside, choose another transform, or leave it out of trainable")
    index = {name: names.index(name) for name in trainable}

    def to_params(coords: dict) -> Any:
        new = list(leaves)
        for name, i in index.items():
            new[i] = transforms[name].to_constrained_fn(coords[name]).astype(jnp.asarray(leaves[i]).dtype)
        return jax.tree.unflatten(treedef, new)

    coords = {name: transforms[name].to_unconstrained_fn(jnp.asarray(leaves[i], jnp.float32))
              for name, i in index.items()}
    return trainable, transforms, to_params, coords


def _run_fit(key: PRNGKeyArray, num_steps: int, update, to_params, coords: dict, state: AdamState,
             trainable: list[str], transforms: dict[str, Transform], progress: bool) -> FitResult:
    """:func:`fit`'s steps: ``update(step_key, coords, state) -> (objective, finite gradient per
    name, new coords, new state)`` once per step key, the constrained values and objective
    recorded before each update; a :class:`FitError` at the first non-finite step."""
    history: dict[str, list] = {"objective": [], **{name: [] for name in trainable}}
    bar = tqdm(jax.random.split(key, num_steps), desc="fit", unit="step", disable=not progress)
    for step_number, step_key in enumerate(bar):
        value, finite, new_coords, new_state = update(step_key, coords, state)
        bad = [name for name in trainable if not bool(finite[name])]
        if bad or not np.isfinite(float(value)):
            so_far = FitResult(to_params(coords), {k: np.asarray(v) for k, v in history.items()}, state)
            raise FitError(f"fit step {step_number}: the objective is {float(value)} and the gradient is not finite "
                           f"in {bad}: "
                           f"the estimate lost every particle at some step, or a filter's map pools overflowed "
                           f"(rbpf.filter then returns -inf: pass a larger pool); the fit stopped, its result up "
                           f"to step {step_number - 1} is in this error's .result", so_far)
        for name in trainable:
            history[name].append(float(transforms[name].to_constrained_fn(coords[name])))
        history["objective"].append(float(value))
        coords, state = new_coords, new_state
        bar.set_postfix(objective=f"{float(value):.3f}")
    return FitResult(to_params(coords), {k: np.asarray(v) for k, v in history.items()}, state)


def structurally_zero(objective_fn: Callable[[dict], Float[Array, ""]], coords: dict) -> list[str]:
    """The names in ``coords`` (a dict of scalars) on which ``objective_fn(coords)`` cannot depend
    differentiably: autodiff's gradient for them is the constant 0 of the traced program, not a
    value that happens to be 0 (found by tracing the gradient, without running it)."""
    jaxpr = jax.make_jaxpr(jax.grad(objective_fn))(coords)
    names = sorted(coords)  # a dict's leaves come in key order
    return [name for name, var in zip(names, jaxpr.jaxpr.outvars) if isinstance(var, Literal)]


LEARNING_SETTINGS: dict[str, Any] = {
    "likelihood.gain": 1.0,           # the untempered likelihood: a tempered one peaks elsewhere
    "likelihood_lookup": "bilinear",  # weights continuous in the pose (the fits in docs/results.md use it)
    "smp_weight": "importance",       # the SMP's proper weight: its gradient is the drawn pose's score
    # The stencil the SMP's Gaussian is fitted on (and the floor of its std, a tenth of it): finer
    # than a step's posterior when every scan is an update (the default 5 cm and 0.05 rad are for
    # half-metre steps; at 1 cm the office's weights keep twice the ESS: docs/results.md).
    "scan_match.linear_step": 0.01,
    "scan_match.angular_step": 0.01,
    "linear_update": 0.0,             # every scan an update: the motion model is the one that made the data
    "angular_update": 0.0,
}
"""What a fit of the RBPF's parameters needs beyond the mapping defaults (docs/design.md,
"Tempering and learning")."""


def slam_learning_setup(values: dict[str, Any] | None = None):
    """``(config, settings, params)`` of the RBPF set up for learning: :data:`LEARNING_SETTINGS`
    over the library's defaults, then ``values`` (names as ``--set`` takes them: config fields,
    run settings and dotted parameters; e.g. the data's minimum stds ``motion.min_translation_std``
    and ``motion.min_rotation_std`` where they are known, as for a simulated log). A value in
    ``values`` that undoes a learning setting is kept but warned of."""
    values = dict(values or {})
    undone = sorted(k for k, v in values.items() if k in LEARNING_SETTINGS and v != LEARNING_SETTINGS[k])
    if undone:
        warn(f"slam_learning_setup: {undone} differ from what learning needs ({LEARNING_SETTINGS}); the "
             f"log-likelihood then does not peak at the data's parameters")
    return build_setup({**LEARNING_SETTINGS, **values})


class FitError(FloatingPointError):
    """:func:`fit` met a non-finite objective or gradient; ``result`` is the fit before that step."""

    def __init__(self, message: str, result: FitResult):
        super().__init__(message)
        self.result = result

