"""experiments/free_space_bias.py on one lap of one world: the truth crosses few cells, and a map that
holds X's landmarks twice makes the true poses near X cross many."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import free_space_bias  # noqa: E402


def test_a_landmark_held_twice_is_crossed_and_the_truth_is_not_far_from_the_least_crossed():
    counts, twice, num_scans, num_near = free_space_bias.crossing_counts(1000, first=0, every=25, rotation_deg=10.0,
                                                                          max_laps=1)
    assert num_scans > 5 and num_near > 20
    assert counts[0] <= num_scans / 4  # at most one crossing beam in four scans at the truth (of 90 beams a scan)
    assert counts[0] <= counts.min() + 2  # no pose nearby crosses much less: little pull to any side
    assert counts[8] > counts[0] + num_scans  # 0.2 m back crosses more than once a scan
    assert twice[1] > twice[0] + num_near  # the landmarks held twice: more than one more crossing a scan near X
