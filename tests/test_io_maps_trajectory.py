"""Map files (PGM/PNG + YAML, ROS map_server) and per-scan trajectories (fill-in, text files)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from jaxslam.geometry import between, compose
from jaxslam.grid import GridSpec
from jaxslam.io import (
    read_map,
    read_trajectory,
    write_map,
    write_trajectory,
)
from jaxslam.laserlog import LaserLog, LogError, poses_at, trajectory_per_scan
from jaxslam.io.maps import DEFAULT_MARGIN_CELLS, crop_to_known
from jaxslam.laser import make_sensor, uniform_beams

# --------------------------------------------------------------------------- maps


def _test_grid():
    """A 4 x 6 grid: occupied bottom-left cell, a free row, unknown elsewhere, one
    borderline cell each side of the thresholds."""
    logodds = np.zeros((4, 6), np.float32)
    logodds[0, 0] = 3.0  # occupied, at the origin (bottom-left in the world, bottom row of the image)
    logodds[1, :] = -3.0  # free
    logodds[3, 5] = 0.7  # p = 0.668 > 0.65: occupied (top-right)
    logodds[3, 4] = 0.5  # p = 0.622: unknown
    logodds[2, 1] = -1.3  # p = 0.214: unknown
    logodds[2, 2] = -1.5  # p = 0.182 < 0.196: free
    spec = GridSpec((4, 6), 0.05, (-1.25, 2.5))
    return logodds, spec


def _expected_probability(logodds):
    p = 1 / (1 + np.exp(-logodds.astype(np.float64)))
    return np.where(p > 0.65, 1.0, np.where(p < 0.196, 0.0, 0.5)).astype(np.float32)


def test_write_map_files(tmp_path):
    logodds, spec = _test_grid()
    paths = write_map(tmp_path / "office", logodds, spec)
    assert set(paths) == {"pgm", "yaml", "png"} and all(p.is_file() for p in paths.values())
    data = paths["pgm"].read_bytes()
    assert data.startswith(b"P5\n")
    assert b"\n6 4\n255\n" in data
    pixels = np.frombuffer(data[-24:], np.uint8).reshape(4, 6)
    # Image rows are top-down: image row 3 is grid row 0.
    assert pixels[3, 0] == 0 and pixels[0, 5] == 0
    assert np.all(pixels[2] == 254) and pixels[1, 2] == 254
    assert pixels[0, 4] == 205 and pixels[1, 1] == 205 and pixels[0, 0] == 205
    assert set(np.unique(pixels)) == {0, 205, 254}
    text = paths["yaml"].read_text()
    assert "image: office.pgm\n" in text and "resolution: 0.05\n" in text
    assert "origin: [-1.25, 2.5, 0.0]\n" in text and "negate: 0\n" in text
    assert "occupied_thresh: 0.65\n" in text and "free_thresh: 0.196\n" in text


def test_map_yaml_origin_is_rounded_to_the_nanometre(tmp_path):
    """An origin computed as start + cells * resolution carries float noise; map.yaml shows the
    number, not the noise, and reads back within a nanometre."""
    logodds, _ = _test_grid()
    noisy = (-12.350000000000001, 0.1 + 0.2)  # 0.30000000000000004
    paths = write_map(tmp_path / "office", logodds, GridSpec((4, 6), 0.05, noisy))
    assert "origin: [-12.35, 0.3, 0.0]\n" in paths["yaml"].read_text()
    assert read_map(paths["yaml"])[1].origin == pytest.approx(noisy, abs=1e-9)
    paths = write_map(tmp_path / "zero", logodds, GridSpec((4, 6), 0.05, (-1e-12, 1.0000000004)))
    assert "origin: [0.0, 1.0, 0.0]\n" in paths["yaml"].read_text()  # no "-0.0"


def test_map_round_trip(tmp_path):
    logodds, spec = _test_grid()
    paths = write_map(tmp_path / "office", logodds, spec)
    probability, read_spec = read_map(paths["yaml"])
    assert read_spec == spec
    assert probability.dtype == np.float32 and not np.any(np.isnan(probability))
    np.testing.assert_array_equal(probability, _expected_probability(logodds))


def test_png_matches_pgm(tmp_path):
    logodds, spec = _test_grid()
    paths = write_map(tmp_path / "office", logodds, spec)
    png_yaml = tmp_path / "png.yaml"
    png_yaml.write_text(paths["yaml"].read_text().replace("office.pgm", "office.png"))
    from_png, png_spec = read_map(png_yaml)
    from_pgm, _ = read_map(paths["yaml"])
    np.testing.assert_array_equal(from_png, from_pgm)
    assert png_spec == spec


def test_map_round_trip_with_jax_input_and_custom_thresholds(tmp_path):
    import jax.numpy as jnp

    logodds, spec = _test_grid()
    paths = write_map(tmp_path / "m", jnp.asarray(logodds), spec, occupied_thresh=0.9, free_thresh=0.1)
    probability, _ = read_map(paths["yaml"])
    p = 1 / (1 + np.exp(-logodds.astype(np.float64)))
    np.testing.assert_array_equal(probability, np.where(p > 0.9, 1.0, np.where(p < 0.1, 0.0, 0.5)))


def test_write_map_rejects_bad_input(tmp_path):
    logodds, spec = _test_grid()
    with pytest.raises(ValueError, match="shape"):
        write_map(tmp_path / "m", logodds.T, spec)
    with pytest.raises(ValueError, match="finite"):
        write_map(tmp_path / "m", np.full(spec.shape, np.nan), spec)
    with pytest.raises(ValueError, match="free_thresh"):
        write_map(tmp_path / "m", logodds, spec, occupied_thresh=0.4)


def test_standard_map_server_map(tmp_path):
    """A hand-written map_server map: ASCII PGM with comments, negate 1, relative image path."""
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "lab.pgm").write_text(
        "P2\n# made by hand\n3 2\n# max\n255\n"
        "255 0 128\n"
        "0 200 30\n"
    )
    yaml_path = tmp_path / "lab.yaml"
    yaml_path.write_text(
        "image: maps/lab.pgm\nresolution: 0.1\norigin: [1.0, -2.0, 0.0]\nnegate: 1\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    probability, spec = read_map(yaml_path)
    assert spec == GridSpec((2, 3), 0.1, (1.0, -2.0))
    # negate 1: occupancy = v / 255. Image row 0 (top) is grid row 1.
    np.testing.assert_array_equal(probability, [[0.0, 1.0, 0.0], [1.0, 0.0, 0.5]])


def test_scale_mode(tmp_path):
    (tmp_path / "s.pgm").write_bytes(b"P5 3 1 255\n" + bytes([0, 255, 166]))
    yaml_path = tmp_path / "s.yaml"
    yaml_path.write_text("image: s.pgm\nmode: scale\nresolution: 1\norigin: [0, 0, 0]\n"
                         "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    probability, _ = read_map(yaml_path)
    occ = (255 - 166) / 255
    np.testing.assert_allclose(probability[0], [1.0, 0.0, (occ - 0.196) / (0.65 - 0.196)], rtol=1e-6)


@pytest.mark.parametrize(
    "yaml_text, match",
    [
        ("resolution: 0.05\norigin: [0, 0, 0]\n", r"missing key\(s\) \['image'\]"),
        ("image: m.pgm\norigin: [0, 0, 0]\n", r"missing key\(s\) \['resolution'\]"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nresoluton: 1\n", r"unknown key\(s\) \['resoluton'\]"),
        ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", r"'resolution' must be positive"),
        ("image: m.pgm\nresolution: fine\norigin: [0, 0, 0]\n", r"'resolution' must be a finite number"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0]\n", None),
        ("image: m.pgm\nresolution: 0.05\norigin: 7\n", r"'origin' must be \[x, y, yaw\]"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0.5]\n", r"'origin' yaw 0\.5 is not 0; rotated maps are not supported"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 2\n", r"'negate' must be 0 or 1"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nfree_thresh: 0.9\n", r"free_thresh 0\.9 must be below"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: fancy\n", r"'mode' must be one of"),
        ("image: m.pgm\nresolution: [0.05\n", r"not valid YAML"),
        ("- just\n- a list\n", r"expected a mapping"),
    ],
)
def test_read_map_bad_yaml(tmp_path, yaml_text, match):
    (tmp_path / "m.pgm").write_bytes(b"P5\n2 1\n255\n" + bytes([0, 254]))
    yaml_path = tmp_path / "m.yaml"
    yaml_path.write_text(yaml_text)
    if match is None:  # a 2-element origin is accepted (yaw 0)
        assert read_map(yaml_path)[1].origin == (0.0, 0.0)
        return
    with pytest.raises(LogError, match=re.escape(str(yaml_path)) + ": " + match):
        read_map(yaml_path)


def test_read_map_bad_image(tmp_path):
    yaml_path = tmp_path / "m.yaml"
    yaml_path.write_text("image: nowhere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(LogError, match=re.escape(str(yaml_path)) + r": the map image .*nowhere\.pgm.* does not exist"):
        read_map(yaml_path)
    with pytest.raises(LogError, match=r"no such map YAML file"):
        read_map(tmp_path / "missing.yaml")
    truncated = tmp_path / "t.pgm"
    truncated.write_bytes(b"P5\n4 4\n255\n" + bytes(10))
    yaml_path.write_text("image: t.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(LogError, match=r"t\.pgm: truncated PGM: 10 bytes of pixels, expected 16"):
        read_map(yaml_path)
    garbage = tmp_path / "g.png"
    garbage.write_bytes(b"not an image at all")
    yaml_path.write_text("image: g.png\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(LogError, match=r"g\.png: cannot read the map image"):
        read_map(yaml_path)


# --------------------------------------------------------------------------- cropping


def _sparse_grid():
    """A 60 x 80 grid, known cells in rows 2..40 and columns 30..71 (row 2 near the bottom
    edge, so a margin of 5 is clipped there), a weakly known cell that maps to unknown."""
    logodds = np.zeros((60, 80), np.float32)
    logodds[2, 40] = 3.0  # occupied, 2 rows from the bottom edge
    logodds[20:26, 30:50] = -2.0  # free
    logodds[40, 71] = 2.5  # occupied: top-right of the known box
    logodds[30, 35] = 0.1  # known (not 0) though its pixel is unknown
    spec = GridSpec((60, 80), 0.05, (-3.2, 1.7))
    return logodds, spec


def test_crop_to_known_shape_and_origin():
    logodds, spec = _sparse_grid()
    cropped, crop_spec = crop_to_known(logodds, spec, margin_cells=5)
    # Rows 2..40 known: 0 (2 - 5 clipped) .. 45; columns 30..71: 25 .. 76 inclusive.
    assert cropped.shape == crop_spec.shape == (46, 52)
    assert crop_spec.resolution == spec.resolution
    assert crop_spec.origin == pytest.approx((-3.2 + 25 * 0.05, 1.7 + 0 * 0.05), abs=1e-12)
    np.testing.assert_array_equal(cropped, logodds[0:46, 25:77])
    # No margin: exactly the known bounding box.
    tight, tight_spec = crop_to_known(logodds, spec, margin_cells=0)
    assert tight.shape == tight_spec.shape == (39, 42)
    assert tight_spec.origin == pytest.approx((-3.2 + 30 * 0.05, 1.7 + 2 * 0.05), abs=1e-12)
    # A margin larger than the grid keeps the whole grid and its origin.
    whole, whole_spec = crop_to_known(logodds, spec, margin_cells=1000)
    assert whole_spec == spec and np.array_equal(whole, logodds)
    # The default margin is DEFAULT_MARGIN_CELLS, clipped to the grid: rows 0..60, cols 10..80.
    default, default_spec = crop_to_known(logodds, spec)
    assert DEFAULT_MARGIN_CELLS == 20
    assert default.shape == default_spec.shape == (60, 70)
    assert default_spec.origin == pytest.approx((-3.2 + 10 * 0.05, 1.7), abs=1e-12)


def test_crop_keeps_every_known_cell_at_its_world_position(tmp_path):
    logodds, spec = _sparse_grid()
    cropped, crop_spec = crop_to_known(logodds, spec, margin_cells=3)
    assert cropped.size < logodds.size
    full_prob, full_spec = read_map(write_map(tmp_path / "full", logodds, spec)["yaml"])
    crop_prob, read_spec = read_map(write_map(tmp_path / "crop", cropped, crop_spec)["yaml"])
    assert read_spec.shape == cropped.shape and read_spec.origin == pytest.approx(crop_spec.origin, abs=1e-12)
    res = spec.resolution
    rows, cols = np.nonzero(logodds)
    assert rows.size == 6 * 20 + 3
    # World centres of the known cells of the uncropped map ...
    x = full_spec.origin[0] + (cols + 0.5) * res
    y = full_spec.origin[1] + (rows + 0.5) * res
    # ... fall into cells of the cropped map that hold the same value.
    crop_cols = np.floor((x - read_spec.origin[0]) / res).astype(int)
    crop_rows = np.floor((y - read_spec.origin[1]) / res).astype(int)
    assert np.all((crop_rows >= 0) & (crop_rows < read_spec.shape[0]))
    assert np.all((crop_cols >= 0) & (crop_cols < read_spec.shape[1]))
    np.testing.assert_array_equal(crop_prob[crop_rows, crop_cols], full_prob[rows, cols])
    assert set(np.unique(crop_prob[crop_rows, crop_cols])) == {0.0, 0.5, 1.0}
    # Every cell of the cropped map, known or not, is the uncropped one at the same place.
    r, c = np.indices(crop_prob.shape)
    full_r = np.floor((read_spec.origin[1] + (r + 0.5) * res - full_spec.origin[1]) / res).astype(int)
    full_c = np.floor((read_spec.origin[0] + (c + 0.5) * res - full_spec.origin[0]) / res).astype(int)
    np.testing.assert_array_equal(crop_prob, full_prob[full_r, full_c])


def test_crop_of_an_all_unknown_map_still_writes(tmp_path):
    spec = GridSpec((30, 40), 0.1, (5.0, -2.0))
    cropped, crop_spec = crop_to_known(np.zeros(spec.shape, np.float32), spec)
    assert cropped.shape == crop_spec.shape == (1, 1) and crop_spec.origin == spec.origin
    paths = write_map(tmp_path / "empty", cropped, crop_spec)
    probability, read_spec = read_map(paths["yaml"])
    assert read_spec == crop_spec
    np.testing.assert_array_equal(probability, np.full((1, 1), 0.5, np.float32))


def test_crop_rejects_bad_input():
    logodds, spec = _sparse_grid()
    with pytest.raises(ValueError, match="shape"):
        crop_to_known(logodds[:10], spec)
    for margin in (-1, 2.5, True):
        with pytest.raises(ValueError, match="margin_cells"):
            crop_to_known(logodds, spec, margin_cells=margin)


def test_map_command_writes_the_cropped_map(tmp_path):
    """A robot driving 2 m in a 2 m-range ring, on a grid padded by 10 m: the map files hold
    only the known area plus the margin, and map.yaml's origin is that crop's corner."""
    from jaxslam.cli import main

    lines = []
    for i in range(6):
        x, t = 0.4 * i, 1000.0 + 0.5 * i
        ranges = " ".join(["2.000"] * 181)
        lines.append(f"FLASER 181 {ranges} {x:.6f} 0.0 0.0 {x:.6f} 0.0 0.0 {t:.6f} host {t:.6f}")
    log_path = tmp_path / "ring.clf"
    log_path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(["map", str(log_path), "--particles", "2", "--proposal", "op", "--no-progress",
                 "--set", "linear_update=0.3", "--set", "max_insert_range=3",
                 "--out", str(out)]) == 0
    probability, spec = read_map(out / "map.yaml")
    grid = GridSpec.from_bounds(-10.0, -10.0, 12.0, 10.0, 0.05)  # the odometry's extent padded by 10 m
    assert spec.shape[0] < grid.shape[0] and spec.shape[1] < grid.shape[1]
    assert spec.origin[0] > grid.origin[0] + 5.0 and spec.origin[1] > grid.origin[1] + 5.0
    # The known area (the ring's front halves: x in [0, 4], y in [-2, 2], give or take a cell
    # and the particles' noise) plus the 1 m margin.
    xmin, xmax, ymin, ymax = spec.extent
    assert -1.5 < xmin < -0.5 and 4.5 < xmax < 5.5 and -3.5 < ymin < -2.5 and 2.5 < ymax < 3.5
    col, row = int((1.0 - spec.origin[0]) / spec.resolution), int((0.0 - spec.origin[1]) / spec.resolution)
    assert probability[row, col] == 0.0  # 1 m ahead of the start: seen free by the first scans
    assert probability[0, 0] == 0.5 and probability[-1, -1] == 0.5  # the margin is unknown


# --------------------------------------------------------------------------- trajectories


def _odometry_log(num_scans=12, seed=0):
    rng = np.random.default_rng(seed)
    steps = np.column_stack([rng.uniform(0.0, 0.3, num_scans), rng.normal(0, 0.05, num_scans),
                             rng.normal(0, 0.2, num_scans)])
    odom = np.zeros((num_scans, 3))
    for i in range(1, num_scans):
        odom[i] = np.asarray(compose(odom[i - 1], steps[i]))
    sensor = make_sensor(uniform_beams(3), range_max=10.0)
    return LaserLog(100.0 + 0.1 * np.arange(num_scans), odom, np.ones((num_scans, 3)), sensor)


def test_trajectory_with_odometry_poses_is_the_odometry():
    log = _odometry_log()
    idx = np.array([2, 5, 9])
    traj = trajectory_per_scan(log, idx, log.odometry[idx])
    np.testing.assert_allclose(traj, log.odometry, atol=1e-5)


def test_trajectory_with_a_rigidly_moved_estimate():
    """When every processed pose is the odometry moved by one rigid transform, so is every scan."""
    log = _odometry_log()
    offset = np.array([3.0, -1.0, 2.5])
    moved = np.asarray(compose(offset, log.odometry), dtype=np.float64)
    idx = np.array([3, 4, 10])
    traj = trajectory_per_scan(log, idx, moved[idx])
    np.testing.assert_allclose(traj, moved, atol=1e-5)


def test_trajectory_fill_in_formula():
    log = _odometry_log()
    idx = np.array([3, 7])
    processed = np.array([[1.0, 2.0, 0.3], [1.5, 2.5, -3.1]])
    traj = trajectory_per_scan(log, idx, processed)
    assert traj.shape == (log.num_scans, 3) and traj.dtype == np.float64
    np.testing.assert_array_equal(traj[idx], processed)  # processed scans keep their poses exactly
    odom = log.odometry
    for i in range(log.num_scans):
        k = 0 if i < 7 else 1  # scans 0..2 hang off the first processed scan too
        expected = np.asarray(compose(processed[k], between(odom[idx[k]], odom[i])))
        np.testing.assert_allclose(traj[i], expected, atol=1e-5)
    assert np.all(np.abs(traj[:, 2]) <= math.pi)


def test_trajectory_wraps_processed_headings():
    log = _odometry_log()
    traj = trajectory_per_scan(log, [0], [[0.0, 0.0, 2 * math.pi + 0.5]])
    assert traj[0, 2] == pytest.approx(0.5)
    assert np.all((traj[:, 2] > -math.pi) & (traj[:, 2] <= math.pi))


def test_trajectory_rejects_bad_indices():
    log = _odometry_log()
    pose = np.zeros((2, 3))
    with pytest.raises(ValueError, match="strictly increasing"):
        trajectory_per_scan(log, [4, 4], pose)
    with pytest.raises(ValueError, match=r"must lie in \[0, 12\)"):
        trajectory_per_scan(log, [4, 12], pose)
    with pytest.raises(ValueError, match="shape"):
        trajectory_per_scan(log, [4, 5], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="at least one"):
        trajectory_per_scan(log, [], np.zeros((0, 3)))


def test_trajectory_file_round_trip(tmp_path):
    timestamps = np.array([976052857.337530017, 976052857.348896027, 976052858.0])
    poses = np.array([[0.0, 0.0, 0.0], [1.123456789, -2.5, 3.14159], [1e-9, 42.0, -1.0]])
    path = tmp_path / "traj.txt"
    write_trajectory(path, timestamps, poses)
    text = path.read_text()
    assert text.startswith("# ")
    assert "976052857.337530017" in text or "976052857.337530" in text
    read_ts, read_poses = read_trajectory(path)
    np.testing.assert_array_equal(read_ts, timestamps)  # 9 decimals: a float64 round trip
    np.testing.assert_allclose(read_poses, poses, atol=1e-9)


@pytest.mark.parametrize(
    "body, line_no, match",
    [
        ("1.0 0 0 0\n2.0 0 0\n", 3, r"expected 4 fields"),
        ("1.0 0 0 0\n2.0 0 zero 0\n", 3, r"non-numeric field"),
        ("1.0 0 0 nan\n", 2, r"non-finite value"),
        ("2.0 0 0 0\n\n1.0 0 0 0\n", 4, r"timestamp goes backwards"),
    ],
)
def test_read_trajectory_errors(tmp_path, body, line_no, match):
    path = tmp_path / "traj.txt"
    path.write_text("# header\n" + body)
    with pytest.raises(LogError, match=re.escape(f"{path}:{line_no}: ") + match):
        read_trajectory(path)


def test_read_trajectory_empty_or_missing(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# only a header\n")
    with pytest.raises(LogError, match=r"holds no poses"):
        read_trajectory(path)
    with pytest.raises(LogError, match=r"no such trajectory file"):
        read_trajectory(tmp_path / "missing.txt")


def test_warnings_point_at_the_callers_line(tmp_path):
    """A warning from inside the package names the user's call (here: this file), not the
    reader's internals, whichever entry point was called."""
    import warnings

    from jaxslam.io import read_log
    from logs import write_flaser_log

    path = tmp_path / "traj.txt"
    path.write_text("0 0 0 0\n1 5 5 0\n1 1 0 0\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_trajectory(path)
    assert [w.filename for w in caught] == [__file__], [(w.filename, w.lineno) for w in caught]
    clf = tmp_path / "log.clf"
    from jaxslam.sim import office_scenario
    import jax

    write_flaser_log(clf, office_scenario(jax.random.key(0), num_scans=20, num_beams=31).log.subset(np.arange(6)))
    lines = clf.read_text().splitlines()
    odom = [f"ODOM 0 0 0 0 0 0 {t:.6f} host {t:.6f}" for t in (float(line.split()[-3]) - 0.01 for line in lines[1:])]
    # ODOM lines before every laser line but the last: the last is dropped, with a warning.
    clf.write_text("\n".join([lines[0], *(x for pair in zip(odom, lines[1:]) for x in pair)][:-2] + lines[-1:]) + "\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_log(clf, odometry_source="odom")
    assert caught and {w.filename for w in caught} == {__file__}, [(w.filename, str(w.message)) for w in caught]


def test_write_trajectory_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_trajectory(tmp_path / "t.txt", [1.0, 2.0], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="finite"):
        write_trajectory(tmp_path / "t.txt", [1.0], [[np.nan, 0, 0]])


def test_poses_at():
    times = np.array([0.0, 1.0, 1.0, 2.0])  # a repeated timestamp (as in the ACES odometry)
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, math.pi / 2]])
    result = poses_at([-0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5], times, poses)
    np.testing.assert_array_equal(result.covered, [False, True, True, True, True, True, False])
    np.testing.assert_allclose(result.poses[1:4], [[0, 0, 0], [0.5, 0, 0], [1, 0, 0]], atol=1e-6)
    np.testing.assert_array_equal(result.poses[5], poses[3])
    assert np.all(np.isfinite(result.poses))
    # Half of a quarter turn along the arc-free relative motion: the pose of geometry.interpolate.
    assert result.poses[4, 2] == pytest.approx(math.pi / 4, abs=1e-6)
