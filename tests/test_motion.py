"""The odometry motion model (jaxslam.motion): noise stds, sampling, log-density."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import motion as M

PARAMS = M.motion_params(0.1, 0.2, 0.1, 0.2, 0.01, 0.005)
POSE = np.array([1.0, 2.0, 0.7], np.float32)
MOTION = np.array([0.5, 0.1, 0.3], np.float32)
N = 200_000


def test_motion_params_is_float32_and_checked():
    params = M.motion_params(0.1, 0.2, np.float64(0.1), jnp.float32(0.2), 0.01)
    assert all(v.dtype == jnp.float32 and v.shape == () for v in params)
    assert float(params.str) == pytest.approx(0.1) and float(params.min_rotation_std) == 0.0
    for bad in (-0.1, float("nan"), float("inf"), [0.1, 0.2], "0.1"):
        with pytest.raises(ValueError, match="srt must be a finite number >= 0"):
            M.motion_params(0.1, bad, 0.1, 0.2)
    # Traced values pass unchecked (a fit differentiates through the constructor).
    grad = jax.grad(lambda v: M.motion_params(v, 0.0, 0.0, 0.0, 0.01, 0.0).srr * 2.0)(jnp.float32(0.3))
    assert float(grad) == 2.0

log_density = jax.jit(M.log_density)
sample = jax.jit(M.sample)


def np_noise_std(u, p):
    srr, srt, strr, stt, mt, mr = (float(v) for v in p)
    ax, ay, ath = abs(u[0]), abs(u[1]), abs(u[2])
    return np.array([
        srr * ax + 0.3 * srr * ay + srt * ath + mt,
        srr * ay + 0.3 * srr * ax + srt * ath + mt,
        stt * ath + strr * np.hypot(u[0], u[1]) + mr,
    ])


def np_between(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    dth = (b[..., 2] - a[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dth], axis=-1)


def np_log_density(new, pose, u, p):
    std = np_noise_std(np.asarray(u, np.float64), p)
    r = np_between(pose, new) - np.asarray(u, np.float64)
    r[..., 2] = (r[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return np.sum(-0.5 * (r / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi), axis=-1)


@pytest.mark.parametrize("u", [MOTION, np.array([-0.2, 0.4, -1.1]), np.zeros(3), np.array([0.0, 0.0, 2.5])])
def test_noise_std_formula(u):
    np.testing.assert_allclose(np.asarray(M.noise_std(jnp.asarray(u, jnp.float32), PARAMS)),
                               np_noise_std(u, PARAMS), rtol=1e-6)


@pytest.fixture(scope="module")
def samples():
    poses = jnp.broadcast_to(jnp.asarray(POSE), (N, 3))
    out = np.asarray(sample(jax.random.key(0), poses, jnp.asarray(MOTION), PARAMS), np.float64)
    assert out.shape == (N, 3) and np.all(np.isfinite(out))
    return out


def test_sample_mean_and_covariance_in_local_frame(samples):
    std = np_noise_std(MOTION, PARAMS)  # about (0.133, 0.085, 0.115)
    noise = np_between(POSE, samples) - MOTION
    # Mean of each noise component: standard error std / sqrt(N); allow 5 of them.
    np.testing.assert_array_less(np.abs(noise.mean(axis=0)), 5 * std / np.sqrt(N))
    cov = np.cov(noise.T)
    # Sample variance of a Gaussian: relative standard error sqrt(2 / (N - 1)) = 0.32%; allow 5.
    np.testing.assert_allclose(np.diag(cov), std**2, rtol=5 * np.sqrt(2 / (N - 1)))
    # Independent components: sample correlations have standard error 1 / sqrt(N); allow 5.
    corr = cov / np.outer(np.sqrt(np.diag(cov)), np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(corr[np.triu_indices(3, 1)], 0.0, atol=5 / np.sqrt(N))


def test_sample_noise_is_not_in_the_world_frame(samples):
    """The x and y noise stds differ in the robot frame; the world-frame covariance is that
    diagonal rotated by theta = 0.7, which has a clear x-y correlation."""
    std = np_noise_std(MOTION, PARAMS)
    c, s = np.cos(POSE[2]), np.sin(POSE[2])
    rot = np.array([[c, -s], [s, c]])
    want = rot @ np.diag(std[:2] ** 2) @ rot.T
    got = np.cov(samples[:, :2].T)
    # Each covariance entry has a relative standard error of about sqrt(2 / N); 5 of them of the largest.
    np.testing.assert_allclose(got, want, rtol=0, atol=5 * np.sqrt(2 / N) * std[:2].max() ** 2)


def test_world_gaussian_is_the_samples_mean_and_covariance(samples):
    """The prior as a world-frame Gaussian (what the window posterior's fit multiplies by): its
    mean and covariance against 200,000 draws of ``sample``, within 5 Monte Carlo standard
    errors (x_t is linear in the noise, so the Gaussian is exact); a heading-only rotation
    would leave the x-y correlation out and fails."""
    mean, cov = (np.asarray(v, np.float64) for v in M.world_gaussian(jnp.asarray(POSE), jnp.asarray(MOTION), PARAMS))
    std = np.sqrt(np.diag(cov))
    np.testing.assert_array_less(np.abs(samples.mean(axis=0) - mean), 5 * std / np.sqrt(N))
    np.testing.assert_allclose(np.cov(samples.T), cov, rtol=0, atol=5 * np.sqrt(2 / N) * std.max() ** 2)
    assert abs(cov[0, 1]) > 20 * np.sqrt(2 / N) * std.max() ** 2  # the rotated diagonal's correlation is there


def test_sample_broadcasts_over_leading_axes_and_keys_differ():
    poses = jnp.broadcast_to(jnp.asarray(POSE), (2, 3, 3))
    a = np.asarray(sample(jax.random.key(1), poses, jnp.asarray(MOTION), PARAMS))
    assert a.shape == (2, 3, 3)
    assert len(np.unique(a[..., 0])) == 6  # independent noise per pose
    b = np.asarray(sample(jax.random.key(1), poses, jnp.asarray(MOTION), PARAMS))
    np.testing.assert_array_equal(a, b)


def test_log_density_against_numpy_gaussian():
    rng = np.random.default_rng(1)
    std = np_noise_std(MOTION, PARAMS)
    local = MOTION + rng.normal(size=(500, 3)) * std * 2.0
    c, s = np.cos(POSE[2]), np.sin(POSE[2])
    new = np.stack([POSE[0] + c * local[:, 0] - s * local[:, 1],
                    POSE[1] + s * local[:, 0] + c * local[:, 1],
                    POSE[2] + local[:, 2]], axis=-1).astype(np.float32)
    got = np.asarray(log_density(jnp.asarray(new), jnp.asarray(POSE), jnp.asarray(MOTION), PARAMS))
    want = np_log_density(new, POSE, MOTION, PARAMS)
    # float32 residuals of ~1e-7 m against stds of ~0.1 m: errors far below 1e-3 in the log.
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-3)
    # Also with several previous poses (leading axes broadcast).
    poses = np.stack([POSE, POSE + np.float32([0.1, -0.2, 0.3])]).astype(np.float32)
    got2 = np.asarray(log_density(jnp.asarray(new[:2]), jnp.asarray(poses), jnp.asarray(MOTION), PARAMS))
    np.testing.assert_allclose(got2, np_log_density(new[:2], poses, MOTION, PARAMS), atol=2e-3)


def test_log_density_wraps_the_angle_residual():
    u = np.array([0.0, 0.0, 3.1], np.float32)
    pose = np.array([0.0, 0.0, 0.0], np.float32)
    new = np.array([0.0, 0.0, -3.1], np.float32)  # 0.083 rad beyond the motion, across pi
    got = float(log_density(jnp.asarray(new), jnp.asarray(pose), jnp.asarray(u), PARAMS))
    assert got == pytest.approx(float(np_log_density(new, pose, u, PARAMS)), abs=1e-3)


def _grid(lo, hi, n):
    """Midpoints and cell width of n equal cells on [lo, hi]."""
    h = (hi - lo) / n
    return lo + h * (np.arange(n) + 0.5), h


def _integrate_density(lo, hi, n):
    """Midpoint-rule integral of exp(log_density) over the world-frame box [lo, hi] (x, y, theta)."""
    axes = [_grid(lo[i], hi[i], n) for i in range(3)]
    pts = np.stack(np.meshgrid(*[a for a, _ in axes], indexing="ij"), axis=-1).reshape(-1, 3)
    ld = np.asarray(log_density(jnp.asarray(pts, jnp.float32), jnp.asarray(POSE), jnp.asarray(MOTION), PARAMS),
                    np.float64)
    return np.exp(ld).sum() * axes[0][1] * axes[1][1] * axes[2][1]


def _mean_pose():
    c, s = np.cos(POSE[2]), np.sin(POSE[2])
    return np.array([POSE[0] + c * MOTION[0] - s * MOTION[1], POSE[1] + s * MOTION[0] + c * MOTION[1],
                     POSE[2] + MOTION[2]])


def test_log_density_normalises():
    std = np_noise_std(MOTION, PARAMS)
    mean = _mean_pose()
    half = 7 * np.array([std[:2].max(), std[:2].max(), std[2]])
    # The midpoint rule on a smooth density that vanishes (e^-24) at the box edges is accurate
    # far beyond 1e-3 with 56 cells of 0.25 std per axis.
    total = _integrate_density(mean - half, mean + half, 56)
    assert total == pytest.approx(1.0, abs=2e-3)


def test_sample_histogram_matches_density_in_a_box(samples):
    """The fraction of samples in an off-centre world-frame box equals the integral of
    exp(log_density) over it: ties sample() and log_density() to one convention."""
    std = np_noise_std(MOTION, PARAMS)
    mean = _mean_pose()
    lo = mean + np.array([-0.3 * std[0], -1.2 * std[1], -0.5 * std[2]])
    hi = mean + np.array([1.4 * std[0], 0.4 * std[1], 1.5 * std[2]])
    # Smooth integrand, 40 cells per axis over about 1.7 std: midpoint-rule error ~ 1e-4 relative.
    p = _integrate_density(lo, hi, 40)
    assert 0.05 < p < 0.5  # a box that actually tests something
    inside = np.all((samples >= lo) & (samples <= hi), axis=1).mean()
    # Binomial standard error sqrt(p (1 - p) / N) (about 0.0008); allow 5 of them plus 1e-3 of quadrature.
    assert abs(inside - p) < 5 * np.sqrt(p * (1 - p) / N) + 1e-3 * p


def test_zero_motion_with_floors_is_finite():
    zero = jnp.zeros(3)
    std = np.asarray(M.noise_std(zero, PARAMS))
    np.testing.assert_allclose(std, [0.01, 0.01, 0.005], rtol=1e-6)
    pose = jnp.asarray(POSE)
    ld = float(log_density(pose, pose, zero, PARAMS))
    want = -np.sum(np.log([0.01, 0.01, 0.005])) - 1.5 * np.log(2 * np.pi)
    assert ld == pytest.approx(want, abs=1e-3)
    x = np.asarray(sample(jax.random.key(3), jnp.broadcast_to(pose, (100, 3)), zero, PARAMS))
    assert np.all(np.isfinite(x))
    # Noise of the size of the floors, and no more.
    assert np.all(np.abs(np_between(POSE, x)) < 6 * np.array([0.01, 0.01, 0.005]))
    grads = jax.jit(jax.grad(lambda p: M.log_density(x[0], pose, zero, p)))(PARAMS)
    assert all(np.isfinite(float(g)) for g in grads)


def test_gradient_of_log_density_matches_numpy_finite_difference():
    new = jnp.asarray(_mean_pose() + np.array([0.05, -0.02, 0.04]), jnp.float32)
    g = jax.jit(jax.grad(lambda p: M.log_density(new, jnp.asarray(POSE), jnp.asarray(MOTION), p)))(PARAMS)
    base = np.array([float(v) for v in PARAMS], np.float64)
    for i in range(6):
        e = np.zeros(6)
        e[i] = 1e-6
        fd = (np_log_density(np.asarray(new), POSE, MOTION, base + e)
              - np_log_density(np.asarray(new), POSE, MOTION, base - e)) / 2e-6
        assert float(g[i]) == pytest.approx(fd, rel=2e-3, abs=1e-2)


def test_sample_with_score_draws_the_same_and_its_gradient_is_the_score():
    """The same draw as ``sample``; the score term is 0 in value and its gradient in every motion
    parameter is that of log p(draw | pose, u) with the draw held fixed (NumPy central
    differences in float64); no gradient reaches the pose."""
    keys = jax.random.split(jax.random.key(3), 5)
    poses = np.repeat(POSE[None], 5, axis=0)
    drawn, score = jax.vmap(M.sample_with_score, in_axes=(0, 0, None, None))(keys, poses, MOTION, PARAMS)
    np.testing.assert_array_equal(np.asarray(drawn), np.asarray(jax.vmap(M.sample, in_axes=(0, 0, None, None))(
        keys, poses, MOTION, PARAMS)))
    np.testing.assert_array_equal(np.asarray(score), 0.0)

    def total(p, pose):
        return jnp.sum(jax.vmap(M.sample_with_score, in_axes=(0, 0, None, None))(keys, pose, MOTION, p)[1])

    grads, pose_grad = jax.grad(total, argnums=(0, 1))(PARAMS, jnp.asarray(poses))
    np.testing.assert_array_equal(np.asarray(pose_grad), 0.0)
    new = np.asarray(drawn, np.float64)
    base = np.array([float(v) for v in PARAMS])
    for i, name in enumerate(M.MotionParams._fields):
        step = 1e-6
        up, down = base.copy(), base.copy()
        up[i] += step
        down[i] -= step
        want = (np.sum(np_log_density(new, POSE, MOTION, up)) - np.sum(np_log_density(new, POSE, MOTION, down))) / (2 * step)
        assert float(getattr(grads, name)) == pytest.approx(want, rel=1e-3, abs=1e-2), name


def test_sample_with_score_is_finite_without_noise():
    """Every std zero (a known path): the pose is the odometry's, the term and its gradient 0."""
    zero = M.motion_params(0, 0, 0, 0, 0, 0)
    new, score = M.sample_with_score(jax.random.key(0), jnp.asarray(POSE), MOTION, zero)
    grads = jax.grad(lambda p: M.sample_with_score(jax.random.key(0), jnp.asarray(POSE), MOTION, p)[1])(zero)
    assert float(score) == 0.0
    assert all(float(g) == 0.0 for g in grads)
    np.testing.assert_allclose(np.asarray(new), np.asarray(M.sample(jax.random.key(0), POSE, MOTION, zero)))


def test_path_log_density_is_the_numpy_sum_and_peaks_at_the_generating_terms():
    """A path drawn from the model itself (each true motion = odometry + noise with the std at the
    odometry reading): the path's log-density equals the NumPy sum, and its score at the
    generating terms is zero within 3 Monte Carlo standard errors (the Fisher identity)."""
    rng = np.random.default_rng(0)
    num_steps = 4000
    # Odometry readings of a wiggly drive: 0.1-0.3 m steps, turns up to 0.4 rad.
    odometry_motion = np.stack([rng.uniform(0.1, 0.3, num_steps), rng.normal(0, 0.01, num_steps),
                                rng.normal(0, 0.15, num_steps)], axis=1).astype(np.float32)
    noise = np.stack([np_noise_std(u, PARAMS) for u in odometry_motion]) * rng.standard_normal((num_steps, 3))
    path = [np.zeros(3)]
    for u in (odometry_motion + noise).astype(np.float64):
        c, s = np.cos(path[-1][2]), np.sin(path[-1][2])
        path.append(path[-1] + np.array([c * u[0] - s * u[1], s * u[0] + c * u[1], u[2]]))
    path = np.asarray(path, np.float32)
    value = float(M.path_log_density(jnp.asarray(path), jnp.asarray(odometry_motion), PARAMS))
    reference = sum(np_log_density(path[t + 1], path[t], odometry_motion[t], PARAMS) for t in range(num_steps))
    assert value == pytest.approx(reference, rel=1e-4)

    def per_step(log_terms):
        p = PARAMS._replace(srr=jnp.exp(log_terms[0]), srt=jnp.exp(log_terms[1]), str=jnp.exp(log_terms[2]),
                            stt=jnp.exp(log_terms[3]))
        return M.log_density(jnp.asarray(path[1:]), jnp.asarray(path[:-1]), jnp.asarray(odometry_motion), p)

    log_terms = jnp.log(jnp.stack([PARAMS.srr, PARAMS.srt, PARAMS.str, PARAMS.stt]))
    scores = np.asarray(jax.jacrev(per_step)(log_terms), np.float64)  # (T, 4): each step's score
    total = scores.sum(axis=0)
    standard_error = scores.std(axis=0, ddof=1) * np.sqrt(num_steps)
    assert np.all(np.abs(total) < 3 * standard_error), (total, standard_error)
    # The test can fail: the same path scored with every term 20 % wider is off by far more.
    wider = np.asarray(jax.grad(lambda x: jnp.sum(per_step(x)))(log_terms + np.log(1.2)), np.float64)
    assert np.any(np.abs(wider) > 3 * standard_error)
