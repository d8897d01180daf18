"""The pipeline of ``jaxslam map`` (:func:`jaxslam.pipeline.map_log`) and what its outputs draw:
``slam.png`` shows the final map (the closed one) with the refined path, ``map.png`` a scale bar
and the origin, ``graph.png`` the pose graph; ``summary.json``'s timings cover every stage; the
writer only writes."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from matplotlib.collections import LineCollection
from matplotlib.image import AxesImage
from PIL import Image

from jaxslam import refine, slam
from jaxslam.binary_bayes import probability
from jaxslam.config import RunSettings, SlamConfig, default_params
from jaxslam.io.maps import crop_to_known
from jaxslam.outputs import write_slam_outputs
from jaxslam.pipeline import MappedLog, finish_mapping, map_log
from jaxslam.plotting import annotate_map_png, scale_bar_metres, slam_figure
from jaxslam.sim import office_scenario

CONFIG = SlamConfig(num_particles=4, proposal="smp", max_insert_range=10.0, beam_stride=1)
SETTINGS = RunSettings(linear_update=0.25, angular_update=0.25)


@pytest.fixture(scope="module")
def office():
    """The simulated office (120 scans, around both rooms and back: the closure keeps loops), mapped."""
    log = office_scenario(jax.random.key(0), num_scans=120).log
    params = default_params()
    mapped = map_log(jax.random.key(0), log, CONFIG, params, SETTINGS, progress=False)
    assert mapped.closure is not None and mapped.closure.num_loops > 0  # else the tests below say nothing
    return log, params, mapped


def _by_label(ax, label):
    found = [a for a in ax.get_lines() + ax.collections if a.get_label().startswith(label)]
    assert len(found) == 1, [a.get_label() for a in ax.get_lines() + ax.collections]
    return found[0]


def test_map_log_holds_every_stage(office):
    log, _, mapped = office
    assert isinstance(mapped, MappedLog) and mapped.map_name == "closed map"
    assert mapped.closure is mapped.result.closure
    np.testing.assert_array_equal(mapped.trajectory, mapped.closure.trajectory)
    assert mapped.refined.poses.shape == (log.num_scans, 3)
    assert mapped.logodds.shape == mapped.hit_dist2.shape == mapped.grid.shape
    assert set(mapped.timings) == {"closed_map", "refinement"}


def test_slam_png_draws_the_closed_map_with_the_refined_path(office):
    log, _, mapped = office
    ax = slam_figure(mapped, log).axes[0]
    title = ax.get_title()
    assert title.startswith("closed map, refined path"), title
    (image,) = [a for a in ax.get_images() if isinstance(a, AxesImage)]
    closed, _ = crop_to_known(mapped.logodds, mapped.grid)
    filters, _ = crop_to_known(*mapped.result.dense_map()[::2])
    drawn = np.asarray(image.get_array())
    np.testing.assert_array_equal(drawn, probability(closed.astype(np.float32)))
    assert drawn.shape != filters.shape or not np.array_equal(drawn, probability(filters.astype(np.float32)))
    path = _by_label(ax, "refined path")
    np.testing.assert_array_equal(path.get_xdata(), mapped.refined.poses[:, 0])
    np.testing.assert_array_equal(path.get_ydata(), mapped.refined.poses[:, 1])
    faint = _by_label(ax, "filter's path")
    np.testing.assert_array_equal(faint.get_xdata(), mapped.result.best_path[:, 0])
    assert faint.get_alpha() < 0.5
    loops = _by_label(ax, "loops kept")
    assert isinstance(loops, LineCollection) and len(loops.get_segments()) == mapped.closure.num_loops
    closure = mapped.closure
    kept = closure.loops.refused == ""
    ends = {tuple(np.round(s, 9).ravel()) for s in loops.get_segments()}
    for query, submap in zip(closure.loops.query[kept], closure.loops.submap[kept]):
        node = closure.submap_first_node[submap]
        assert tuple(np.round(np.r_[closure.poses[query, :2], closure.poses[node, :2]], 9)) in ends
    np.testing.assert_array_equal(_by_label(ax, "start").get_xydata()[0], mapped.refined.poses[0, :2])
    np.testing.assert_array_equal(_by_label(ax, "end").get_xydata()[0], mapped.refined.poses[-1, :2])


def test_without_loops_or_refinement_the_figure_names_the_filters_map(office):
    log, params, mapped = office
    alone = finish_mapping(log, mapped.result._replace(closure=None), params, refine=False)
    ax = slam_figure(alone, log).axes[0]
    assert ax.get_title().startswith("filter's map, filter's path"), ax.get_title()
    filters, _ = crop_to_known(*mapped.result.dense_map()[::2])
    np.testing.assert_array_equal(ax.get_images()[0].get_array(), probability(filters.astype(np.float32)))
    np.testing.assert_array_equal(_by_label(ax, "filter's path").get_xdata(), mapped.result.trajectory[:, 0])
    closed_only = ax = slam_figure(mapped._replace(refined=None), log).axes[0]
    assert closed_only.get_title().startswith("closed map, closed path"), closed_only.get_title()
    np.testing.assert_array_equal(_by_label(ax, "closed path").get_xdata(), mapped.closure.trajectory[:, 0])


def test_the_figure_fits_the_maps_extent(office):
    log, _, mapped = office
    fig = slam_figure(mapped, log)
    xmin, xmax, ymin, ymax = fig.axes[0].get_xlim() + fig.axes[0].get_ylim()
    width, height = fig.get_size_inches()
    # The axes' box (less the 1.5 in kept for the title and the legend) has the map's aspect.
    aspect = (xmax - xmin) / (ymax - ymin)
    assert abs(width / (height - 1.5) - aspect) < 0.02 * aspect
    from jaxslam.grid import GridSpec
    from jaxslam.plotting import _fitted_figure

    long_map = _fitted_figure(GridSpec((300, 800), 0.05, (0.0, 0.0)))  # 40 m by 15 m
    np.testing.assert_allclose(long_map.get_size_inches(), (9.0, 9.0 * 15 / 40 + 1.5))


def test_map_png_has_a_scale_bar_and_the_origin(office, tmp_path):
    log, params, mapped = office
    write_slam_outputs(tmp_path / "out", log, mapped, params, seed=0, source="test")
    rgb = np.asarray(Image.open(tmp_path / "out" / "map.png").convert("RGB"))
    pgm = np.asarray(Image.open(tmp_path / "out" / "map.pgm"))
    height, width = pgm.shape
    assert rgb.shape[0] > height and rgb.shape[1] == width  # a strip below the map
    spec = crop_to_known(mapped.logodds, mapped.grid)[1]
    col, row = int((0 - spec.origin[0]) // spec.resolution), height - 1 - int((0 - spec.origin[1]) // spec.resolution)
    assert tuple(rgb[row, col]) == (220, 0, 0)  # the origin's cross
    away = np.ones(pgm.shape, bool)
    away[max(row - 10, 0):row + 11, max(col - 10, 0):col + 11] = False
    np.testing.assert_array_equal(rgb[:height][away][:, 0], pgm[away])  # the map's pixels kept
    bar_m = scale_bar_metres(width * spec.resolution)
    strip = rgb[height:, :, 0]
    bar_row = strip[:, :width // 2].min(axis=1).argmin()
    black = np.flatnonzero(strip[bar_row] == 0)
    assert round(bar_m / spec.resolution) == black[np.flatnonzero(np.diff(black) > 1)[0] if np.any(np.diff(black) > 1)
                                                   else -1] - black[0] + 1


def test_scale_bar_lengths():
    widths = (22.0, 4.0, 100.0, 0.9, 7.0, 19.0)
    assert [scale_bar_metres(w) for w in widths] == [5.0, 1.0, 20.0, 0.2, 1.0, 2.0]


def test_an_origin_off_the_map_is_noted_not_drawn(tmp_path):
    from jaxslam.grid import GridSpec

    Image.fromarray(np.full((50, 80), 254, np.uint8)).save(tmp_path / "m.png")
    drawn = annotate_map_png(tmp_path / "m.png", GridSpec((50, 80), 0.05, (10.0, 10.0)))
    assert drawn["origin_px"] is None
    rgb = np.asarray(Image.open(tmp_path / "m.png").convert("RGB"))
    assert not np.any((rgb[..., 0] == 220) & (rgb[..., 1] == 0))


def test_the_writer_only_writes_and_its_timings_cover_every_stage(office, tmp_path, monkeypatch):
    log, params, mapped = office

    def trap(*args, **kwargs):
        raise AssertionError("the writer computed a stage")

    monkeypatch.setattr(slam.SlamResult, "closed_map", trap)
    monkeypatch.setattr(refine, "refine_in_rounds", trap)
    import time

    started = time.perf_counter() - 1.0  # a second of reading before
    summary = write_slam_outputs(tmp_path / "out", log, mapped, params, seed=0, source="test",
                                 timings={"read": 1.0}, started=started)
    assert json.loads((tmp_path / "out" / "summary.json").read_text()) == summary
    t = summary["timings"]
    assert {"compile", "total", "real_time_factor", "closure", "closed_map", "refinement", "read", "write",
            "total_wall"} <= set(t)
    assert t["closed_map"] == mapped.timings["closed_map"] and t["refinement"] == mapped.timings["refinement"]
    assert t["read"] + t["write"] <= t["total_wall"] <= t["read"] + t["write"] + 0.5
    assert (tmp_path / "out" / "graph.png").stat().st_size > 10_000
    closed = np.asarray(Image.open(tmp_path / "out" / "map.pgm"))
    assert closed.shape == crop_to_known(mapped.logodds, mapped.grid)[0].shape


def test_the_refinement_shows_a_progress_bar(office, capsys):
    log, params, mapped = office
    finish_mapping(log, mapped.result, params, refine=True, progress=True)
    err = capsys.readouterr().err
    assert "refinement, round 1 of 2" in err and "refinement, round 2 of 2" in err
    finish_mapping(log, mapped.result, params, refine=True, progress=False)
    assert "refinement" not in capsys.readouterr().err
