"""experiments/closure_stress.py: its faults turn the path as a slow loop over the steps does, and
a bad fault or a missing file is refused before any work."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import closure_stress  # noqa: E402


def _turned_slowly(poses, start, radians, nodes):
    """Reference: walk the path step by step, adding the fault's share of the turn to each step."""
    out = [np.array(poses[0], float)]
    for i in range(1, len(poses)):
        a, b = poses[i - 1], poses[i]
        c, s = np.cos(a[2]), np.sin(a[2])
        step = np.array([c * (b[0] - a[0]) + s * (b[1] - a[1]), -s * (b[0] - a[0]) + c * (b[1] - a[1]), b[2] - a[2]])
        if start <= i - 1 < start + nodes:
            step[2] += radians / nodes
        p = out[-1]
        c, s = np.cos(p[2]), np.sin(p[2])
        out.append(np.array([p[0] + c * step[0] - s * step[1], p[1] + s * step[0] + c * step[1], p[2] + step[2]]))
    return np.array(out)


def test_a_jump_turns_every_later_pose_rigidly_and_a_bend_spreads_the_turn():
    rng = np.random.default_rng(0)
    poses = np.cumsum(rng.normal(0.0, [0.3, 0.3, 0.1], size=(40, 3)), axis=0)
    jumped = closure_stress.turned(poses, "jump:0.5:30")
    np.testing.assert_allclose(jumped[:21], poses[:21], atol=1e-12)
    # Rigid: the distances among the later poses, and the turn between any two of them, are kept.
    later, turned_later = poses[21:, :2], jumped[21:, :2]
    np.testing.assert_allclose(np.linalg.norm(turned_later[:, None] - turned_later[None], axis=-1),
                               np.linalg.norm(later[:, None] - later[None], axis=-1), atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (jumped[21:, 2] - poses[21:, 2]))), np.radians(30.0), atol=1e-12)
    bent = closure_stress.turned(poses, "bend:0.25:20:10")
    reference = _turned_slowly(poses, 10, np.radians(20.0), 10)
    np.testing.assert_allclose(bent[:, :2], reference[:, :2], atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (bent[:, 2] - reference[:, 2]))), 0.0, atol=1e-12)


@pytest.mark.parametrize("extra, problem", [(["--faults", "twist:0.5:30"], "expected jump"),
                                            (["--faults", "jump:1.5:30"], "WHERE must lie"),
                                            (["--faults", "bend:0.5:30"], "expected jump"),
                                            (["--faults", "jump:half:30"], "must be numbers"),
                                            (["--set", "window_width=7"], "no ClosureConfig field"),
                                            (["--set", "window_min_xy=wide"], "is no float"),
                                            (["--set", "window_min_xy=-1"], "window_min_xy must be")])
def test_a_bad_fault_or_closure_setting_is_refused_before_any_work(extra, problem, tmp_path, capsys):
    out = tmp_path / "stress.json"
    with pytest.raises(SystemExit):
        closure_stress.main(["--log", "missing.bag", "--relations", "r", "--trajectory", "t", "--out", str(out),
                             *extra])
    assert problem in capsys.readouterr().err and not out.exists()


def test_a_fault_past_the_path_and_a_missing_log_are_named(tmp_path, capsys):
    with pytest.raises(ValueError, match="run past"):
        closure_stress.turned(np.zeros((10, 3)), "bend:0.5:30:8")
    with pytest.raises(SystemExit):
        closure_stress.main(["--log", str(tmp_path / "missing.bag"), "--relations", "r", "--trajectory", "t",
                             "--out", str(tmp_path / "stress.json")])
    assert "--log" in capsys.readouterr().err


def test_closure_settings_take_each_fields_type():
    from _runs import closure_settings

    assert closure_settings(["window_min_xy=7", "min_support=2", "places_per_query=0"]) == {
        "window_min_xy": 7.0, "min_support": 2, "places_per_query": 0}
    assert isinstance(closure_settings(["window_min_xy=7"])["window_min_xy"], float)
    assert closure_settings([]) == {}
