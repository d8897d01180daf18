"""Log files for tests, written from simulated logs."""

from __future__ import annotations


def write_flaser_log(path, log, stop=None):
    """A CARMEN text log with FLASER lines (odometry inside each line)."""
    lines = ["# synthetic CARMEN log written by the tests"]
    for i in range(log.num_scans if stop is None else stop):
        r = " ".join(f"{v:.3f}" for v in log.ranges[i])
        x, y, th = log.odometry[i]
        t = 1000.0 + log.timestamps[i]
        lines.append(f"FLASER {log.num_beams} {r} {x:.6f} {y:.6f} {th:.6f} {x:.6f} {y:.6f} {th:.6f} {t:.6f} host {t:.6f}")
    path.write_text("\n".join(lines) + "\n")


def cluttered_world(rng, low, high, count: int):
    """``count`` segments 0.5-2 m long at random places and angles in the box ``low``..``high``
    (m): a world where every scan has structure to match, whichever way the robot faces."""
    import numpy as np

    from jaxslam.sim import make_world

    starts = rng.uniform(low, high, size=(count, 2))
    angle = rng.uniform(0, np.pi, count)
    ends = starts + rng.uniform(0.5, 2.0, size=(count, 1)) * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return make_world(np.concatenate([starts, ends], axis=1))
