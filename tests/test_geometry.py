"""Properties of SE(2) pose algebra in jaxslam.geometry (float32 tolerances)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from jaxslam import geometry as G

PI32 = float(np.float32(np.pi))  # float32 pi is slightly above the real pi: the wrap interval is (-PI32, PI32]
N = 4  # poses per example: a fixed shape, so JAX compiles each op once
SETTINGS = settings(max_examples=60, deadline=None)

coord = st.floats(-50.0, 50.0, width=32, allow_nan=False)
angle = st.floats(-PI32, PI32, width=32, allow_nan=False)


@st.composite
def poses(draw, n=N):
    xs = [draw(coord) for _ in range(2 * n)]
    ths = [draw(angle) for _ in range(n)]
    return np.stack([np.array(xs[:n]), np.array(xs[n:]), np.array(ths)], axis=-1).astype(np.float32)


def angle_diff(a, b):
    """Wrapped difference a - b in (-pi, pi], in float64."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    return (d + np.pi) % (2 * np.pi) - np.pi


def assert_pose_close(a, b, scale):
    """Positions within float32 rounding of quantities of size ``scale`` (m); angles within 1e-5 rad."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    # float32 has a relative precision of 6e-8; a handful of chained multiply-adds on
    # coordinates of size `scale` accumulates well under 1e-6 * scale.
    np.testing.assert_allclose(a[..., :2], b[..., :2], rtol=0, atol=1e-6 * scale + 1e-6)
    np.testing.assert_allclose(angle_diff(a[..., 2], b[..., 2]), 0.0, rtol=0, atol=1e-5)


def np_compose(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1],
                     a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     angle_diff(a[..., 2] + b[..., 2], 0.0)], axis=-1)


@SETTINGS
@given(poses(), poses())
def test_compose_matches_numpy_reference(a, b):
    assert_pose_close(G.compose(a, b), np_compose(a, b), scale=200.0)


@SETTINGS
@given(poses(), poses(), poses())
def test_compose_is_associative(a, b, c):
    left = G.compose(G.compose(a, b), c)
    right = G.compose(a, G.compose(b, c))
    assert_pose_close(left, right, scale=300.0)


@SETTINGS
@given(poses())
def test_inverse_cancels(a):
    assert_pose_close(G.compose(a, G.inverse(a)), np.zeros_like(a), scale=150.0)
    assert_pose_close(G.compose(G.inverse(a), a), np.zeros_like(a), scale=150.0)
    assert_pose_close(G.inverse(G.inverse(a)), a, scale=150.0)


@SETTINGS
@given(poses(), poses())
def test_between_is_inverse_compose(a, b):
    assert_pose_close(G.between(a, b), G.compose(G.inverse(a), b), scale=300.0)


@SETTINGS
@given(poses(), poses())
def test_compose_between_recovers_b(a, b):
    assert_pose_close(G.compose(a, G.between(a, b)), b, scale=300.0)


@SETTINGS
@given(poses(), st.lists(coord, min_size=6, max_size=6))
def test_transform_points_agrees_with_compose(pose, flat):
    points = np.asarray(flat, np.float32).reshape(3, 2)
    got = np.asarray(G.transform_points(pose, np.broadcast_to(points, (N, 3, 2))))
    assert got.shape == (N, 3, 2)
    for k in range(3):
        as_pose = np.concatenate([np.broadcast_to(points[k], (N, 2)), np.zeros((N, 1), np.float32)], axis=-1)
        want = np.asarray(G.compose(pose, as_pose))[:, :2]
        np.testing.assert_allclose(got[:, k], want, rtol=0, atol=2e-4)


@SETTINGS
@given(poses(), poses())
def test_interpolate_endpoints_and_midpoint(a, b):
    assert_pose_close(G.interpolate(a, b, 0.0), a, scale=300.0)
    assert_pose_close(G.interpolate(a, b, 1.0), b, scale=300.0)
    # Half way: the relative motion from a is half the relative motion a -> b.
    mid = G.interpolate(a, b, 0.5)
    half = np.asarray(G.between(a, b), np.float64) * 0.5
    assert_pose_close(G.between(a, mid), half, scale=300.0)
    # Per-pose fractions broadcast.
    fr = np.array([0.0, 1.0, 0.0, 1.0], np.float32)
    got = np.asarray(G.interpolate(a, b, fr))
    assert_pose_close(got[0::2], a[0::2], scale=300.0)
    assert_pose_close(got[1::2], b[1::2], scale=300.0)


@settings(max_examples=200, deadline=None)
@given(st.floats(-1e3, 1e3, width=32, allow_nan=False))
@example(np.float32(np.pi))
@example(-np.float32(np.pi))
@example(np.float32(0.0))
@example(np.float32(3 * np.pi))
@example(np.float32(-3 * np.pi))
@example(np.nextafter(np.float32(np.pi), np.float32(4)))
@example(np.nextafter(-np.float32(np.pi), np.float32(-4)))
@example(np.float32(2 * np.pi))
def test_wrap_angle_range_and_congruence(theta):
    theta = np.float32(theta)
    w = float(G.wrap_angle(theta))
    assert -PI32 < w <= PI32
    # w - theta is a multiple of 2 pi (up to float32 rounding of |theta|).
    k = (w - float(theta)) / (2 * np.pi)
    assert abs(k - round(k)) * 2 * np.pi <= 1e-6 * (abs(float(theta)) + 1.0)


def test_wrap_angle_pi_and_minus_pi_map_to_pi():
    assert float(G.wrap_angle(np.float32(np.pi))) == PI32
    assert float(G.wrap_angle(-np.float32(np.pi))) == PI32
    assert float(G.wrap_angle(np.float32(0.0))) == 0.0


def test_wrap_angle_dense_sweep_near_odd_multiples_of_pi():
    """Every float32 within a few thousand ulps of (2k+1) pi wraps into (-pi, pi]."""
    xs = []
    for k in range(-8, 9):
        c = np.float32((2 * k + 1) * np.pi).view(np.int32)
        xs.append(np.arange(c - 2000, c + 2000, dtype=np.int32).view(np.float32))
    xs = np.concatenate(xs)
    w = np.asarray(G.wrap_angle(xs))
    assert np.all(w > -PI32) and np.all(w <= PI32)


def test_make_pose_wraps_and_broadcasts():
    p = np.asarray(G.make_pose(np.array([1.0, 2.0]), 3.0, 4.0))
    assert p.shape == (2, 3)
    np.testing.assert_allclose(p[:, 0], [1.0, 2.0])
    np.testing.assert_allclose(p[:, 1], [3.0, 3.0])
    np.testing.assert_allclose(p[:, 2], 4.0 - 2 * np.pi, atol=1e-6)


@pytest.mark.parametrize("fn", [G.compose, G.between])
def test_leading_axes_broadcast(fn):
    rng = np.random.default_rng(0)
    a = rng.normal(size=(2, 1, 3)).astype(np.float32)
    b = rng.normal(size=(1, 5, 3)).astype(np.float32)
    got = np.asarray(fn(a, b))
    assert got.shape == (2, 5, 3)
    for i in range(2):
        for j in range(5):
            np.testing.assert_allclose(got[i, j], np.asarray(fn(a[i, 0], b[0, j])), atol=1e-6)


def test_wrap_angle_np_matches_jax_version_in_float64():
    from jaxslam.geometry import wrap_angle, wrap_angle_np

    theta = np.concatenate([np.linspace(-20.0, 20.0, 2001), [np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 0.0]])
    wrapped = wrap_angle_np(theta)
    assert wrapped.dtype == np.float64
    assert np.all(wrapped > -np.pi) and np.all(wrapped <= np.pi)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(theta), atol=1e-9)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(theta), atol=1e-9)
    np.testing.assert_allclose(wrapped, np.asarray(wrap_angle(theta.astype(np.float32)), np.float64), atol=1e-5)
    inside = theta[(theta > -np.pi) & (theta <= np.pi)]
    np.testing.assert_array_equal(wrap_angle_np(inside), inside)  # bit for bit in range


def test_between_np_matches_between_and_keeps_float64_precision():
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.uniform(-20, 20, (50, 2)), rng.uniform(-np.pi, np.pi, 50)])
    b = np.column_stack([rng.uniform(-20, 20, (50, 2)), rng.uniform(-np.pi, np.pi, 50)])
    np.testing.assert_allclose(G.between_np(a, b), np.asarray(G.between(a, b)), atol=2e-5)
    # Two poses 1 mm apart, 10 km from the origin: float32 cannot resolve the step, float64 can.
    far = np.array([10_000.0, 10_000.0, 0.3])
    near = far + np.array([0.001, 0.0, 0.0])
    step = G.between_np(far, near)
    np.testing.assert_allclose(np.hypot(step[0], step[1]), 0.001, rtol=1e-9)
    assert G.between_np(far, near).dtype == np.float64


def test_pose_errors_match_numpy():
    rng = np.random.default_rng(0)
    est = rng.normal(size=(50, 3)) * [3.0, 3.0, 4.0]
    truth = rng.normal(size=(50, 3)) * [3.0, 3.0, 4.0]
    position, heading = G.pose_errors(est.astype(np.float32), truth.astype(np.float32))
    diff = np.angle(np.exp(1j * (est[:, 2] - truth[:, 2])))
    np.testing.assert_allclose(np.asarray(position), np.linalg.norm(est[:, :2] - truth[:, :2], axis=1), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(heading), np.abs(diff), atol=1e-5)


def test_chain_np_matches_composing_one_step_at_a_time():
    rng = np.random.default_rng(0)
    start = np.array([3.0, -2.0, 3.0])
    steps = rng.normal(size=(50, 3)) * [0.5, 0.1, 0.4]
    slow = [start]
    for step in steps:
        slow.append(G.compose_np(slow[-1], step))
    np.testing.assert_allclose(G.chain_np(start, steps), np.array(slow), atol=1e-10)
    poses = G.chain_np(start, steps)
    expected = steps.copy()
    expected[:, 2] = G.wrap_angle_np(steps[:, 2])
    np.testing.assert_allclose(G.between_np(poses[:-1], poses[1:]), expected, atol=1e-10)


def test_rotation_np_turns_a_step_as_compose_np_does():
    rng = np.random.default_rng(0)
    poses, steps = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    turned = np.einsum("eij,ej->ei", G.rotation_np(poses[:, 2]), steps[:, :2])
    np.testing.assert_allclose(poses[:, :2] + turned, G.compose_np(poses, steps)[:, :2], atol=1e-12)
    assert G.rotation_np(np.zeros((2, 3))).shape == (2, 3, 2, 2)


def test_between_jacobians_match_finite_differences():
    rng = np.random.default_rng(7)
    a = np.column_stack([rng.normal(0, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)])
    b = np.column_stack([rng.normal(0, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)])
    jac_a, jac_b = G.between_jacobians_np(a, b)
    step = 1e-6
    for k in range(3):
        delta = np.zeros(3)
        delta[k] = step
        for jac, moved in ((jac_a, lambda d: G.between_np(a + d, b)), (jac_b, lambda d: G.between_np(a, b + d))):
            numeric = moved(delta) - moved(-delta)
            numeric[:, 2] = G.wrap_angle_np(numeric[:, 2])
            np.testing.assert_allclose(jac[:, :, k], numeric / (2 * step), atol=1e-6)
    assert G.between_jacobians_np(a[0], b[0])[0].shape == (3, 3)  # one pose pair
