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
