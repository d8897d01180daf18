"""Fitting a filter's parameters to data: Adam on the log-likelihood, in plain JAX.

The filters return an estimate of log p(data | params) whose gradient is the score estimate
(:data:`jaxslam.resampling.RESAMPLING_GRADIENTS`): :func:`fit` climbs it with Adam (Kingma &
Ba 2015; written here, the design card has no optax) over *unconstrained* coordinates, so
that a noise stays positive (log) and a probability inside (0, 1) (logit). Parameters are
addressed by their dotted names (``"motion.srr"``, as ``--set`` and ``default_params`` do);
any of them can be frozen. The optimiser is a ``NamedTuple(init, step)`` of pure functions,
as in optax and blackjax.

    from jaxslam.learning import fit
    result = fit(jax.random.key(0), lambda key, p: rbpf.filter(key, prepared, p, config).marginal_loglik,
                 params, num_steps=50, learning_rate=0.05, trainable=["motion.srr", "likelihood.sigma"])
    result.params, result.history["objective"]
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray


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

    Raises:
      ValueError: before any work, for an unknown trainable name, a starting value outside its
        transform's domain (a zero noise under log), or ``num_steps < 1``.
    """
    if isinstance(num_steps, bool) or not isinstance(num_steps, (int, np.integer)) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")
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
    optimizer = adam(learning_rate)
    state = optimizer.init(coords) if initial_state is None else initial_state

    @jax.jit
    def update(step_key, coords, state):
        value, grads = jax.value_and_grad(lambda c: objective_fn(step_key, to_params(c)))(coords)
        grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, 0.0), grads)  # a NaN step moves nothing
        new_coords, new_state = optimizer.step(state, coords, grads)
        return value, new_coords, new_state

    from tqdm.auto import tqdm

    history: dict[str, list] = {"objective": [], **{name: [] for name in trainable}}
    bar = tqdm(jax.random.split(key, num_steps), desc="fit", unit="step", disable=not progress)
    for step_key in bar:
        for name in trainable:
            history[name].append(float(transforms[name].to_constrained_fn(coords[name])))
        value, coords, state = update(step_key, coords, state)
        history["objective"].append(float(value))
        bar.set_postfix(objective=f"{float(value):.3f}")
    return FitResult(to_params(coords), {k: np.asarray(v) for k, v in history.items()}, state)


MOTION_NOISE_TERMS = ("motion.srr", "motion.srt", "motion.str", "motion.stt")
"""The odometry model's proportional terms (the floors stay as given)."""


OUTLIER_SHARE = 0.05
"""Share of a path's steps :func:`fit_motion_noise` allows to be outliers (a closed loop, a switch
of lineage): they are explained by a flat density instead of widening the model."""
OUTLIER_SPAN = (2.0, 2.0, 2.0 * np.pi)
"""Width (m, m, rad) of the flat outlier density of each residual component."""


def fit_motion_noise(key: PRNGKeyArray, poses, odometry, params, *, num_steps: int = 300,
                     learning_rate: float = 0.05, progress: bool = False) -> FitResult:
    """The odometry noise that explains a path: fit the motion model's proportional terms
    (:data:`MOTION_NOISE_TERMS`) to the differences between a path's steps and the odometry's.

    Each step's residual ``between(x_{t-1}, x_t) - between(o_{t-1}, o_t)`` (per component) is
    modelled as the motion model's Gaussian (std :func:`jaxslam.motion.noise_std` of the
    odometry motion) mixed with a flat density of share :data:`OUTLIER_SHARE`: a path from a
    filter has a few large corrections (a closed loop, a switch of lineage) that a Gaussian fit
    would turn into a wide model. The path can be the filter's own best path over the first
    minutes of a log: no ground truth is needed.

    Args:
      key: seeds :func:`fit` (the objective is deterministic).
      poses: (S, 3) the path at S consecutive processed scans (m, m, rad).
      odometry: (S, 3) the odometry at the same scans.
      params: ``SlamParams`` to start from (the default model); the result keeps its other fields.
      num_steps, learning_rate, progress: of :func:`fit`.

    Returns:
      :class:`FitResult` whose ``params`` hold the fitted terms.

    Raises:
      ValueError: poses and odometry of other shapes, fewer than 10 steps, or a non-finite value.
    """
    from jax.scipy.stats import norm

    from jaxslam.geometry import between_np, wrap_angle
    from jaxslam.motion import noise_std

    poses, odometry = np.asarray(poses, np.float64), np.asarray(odometry, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape != odometry.shape:
        raise ValueError(f"poses and odometry must both be (S, 3), got {poses.shape} and {odometry.shape}")
    if poses.shape[0] < 11:
        raise ValueError(f"at least 10 steps are needed to fit the noise, got {poses.shape[0] - 1}")
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(odometry))):
        raise ValueError("poses and odometry must be finite")
    # Relative motions in float64 on the host (poses may be far from the origin), then float32.
    motions = jnp.asarray(between_np(odometry[:-1], odometry[1:]), jnp.float32)
    residuals = jnp.asarray(between_np(poses[:-1], poses[1:]), jnp.float32) - motions
    residuals = residuals.at[:, 2].set(wrap_angle(residuals[:, 2]))
    log_outlier = math.log(OUTLIER_SHARE) - jnp.log(jnp.asarray(OUTLIER_SPAN, jnp.float32))

    def objective(_, p):
        inlier = math.log1p(-OUTLIER_SHARE) + norm.logpdf(residuals, 0.0, noise_std(motions, p.motion))
        return jnp.sum(jnp.logaddexp(inlier, log_outlier))

    return fit(key, objective, params, num_steps=num_steps, learning_rate=learning_rate,
               trainable=list(MOTION_NOISE_TERMS), progress=progress)


def calibrate_motion(key: PRNGKeyArray, log, config, params, settings=None, *, num_updates: int = 300,
                     progress: bool = False) -> tuple[Any, dict]:
    """Self-calibration of the odometry model from the log itself (no ground truth): map the
    first ``num_updates`` processed scans with the SMP (``config`` with ``proposal="smp"``),
    then fit the motion model's terms to its best path (:func:`fit_motion_noise`).

    The default model (GMapping's) describes no particular robot: FR-clinic's odometry turns
    about ten times more precisely than it says, and with a model that wide the SMP and the
    LP do not hold the heading along long corridors (docs/notes/2026-11-23-motion-model-width.md).

    Args:
      key: the calibration run's key.
      log: the ``LaserLog``; only its first scans up to the ``num_updates``-th processed one are read.
      config, params, settings: the run's (``settings`` default ``RunSettings()``).
      num_updates: updates to calibrate on (>= 10): the first scan and the next ``num_updates`` processed ones.
      progress: show the calibration run's progress bar.

    Returns:
      ``(params, record)``: ``params`` with the fitted motion terms, and ``record`` (for a
      summary): the fitted terms by name, the scans and updates used.
    """
    import dataclasses

    from jaxslam import rbpf
    from jaxslam.config import RunSettings
    from jaxslam.laserlog import select_updates

    if isinstance(num_updates, bool) or not isinstance(num_updates, (int, np.integer)) or num_updates < 10:
        raise ValueError(f"num_updates must be an integer >= 10, got {num_updates!r}")
    settings = RunSettings() if settings is None else settings
    selection = select_updates(log, settings.linear_update, settings.angular_update)
    last = int(selection.indices[min(num_updates, selection.indices.size - 1)])
    head = log.subset(np.arange(last + 1))
    result = rbpf.run(key, head, dataclasses.replace(config, proposal="smp"), params, settings, progress=progress)
    used = result.selection.indices
    if used.size < 11:
        raise ValueError(f"the log has {used.size} processed scans, at least 11 are needed to calibrate the motion")
    fitted = fit_motion_noise(key, result.trajectory[used], np.asarray(head.odometry, np.float64)[used], params)
    record = {name: float(fitted.history[name][-1]) for name in MOTION_NOISE_TERMS}
    record.update(updates=int(used.size), scans=int(head.num_scans))
    return fitted.params, record
