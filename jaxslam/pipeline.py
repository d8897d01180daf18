"""The whole SLAM pipeline of ``jaxslam map`` from Python: :func:`map_log` and its :class:`MappedLog`.

The stages, in order: the filter (:func:`jaxslam.slam.run`), the loop closure behind it
(:func:`jaxslam.graph.close_loops`), the map drawn again at the closed poses
(:meth:`jaxslam.slam.SlamResult.closed_map`) and the refinement, which localises every scan in
that map (:func:`jaxslam.refine.refine_in_rounds`). ``jaxslam map`` calls :func:`map_log`; its
outputs (:func:`jaxslam.outputs.write_slam_outputs`) only write what :func:`map_log` returns.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from jaxtyping import PRNGKeyArray

from jaxslam.config import RunSettings, SlamConfig, SlamParams
from jaxslam.grid import GridSpec
from jaxslam.laserlog import LaserLog, grid_to_world
from jaxslam.refine import RefinedTrajectory, refine_in_rounds, trusts_odometry
from jaxslam.slam import RunProgress, SlamResult, run


class MappedLog(NamedTuple):
    """What :func:`map_log` returns: every stage's result (host arrays, world frame)."""

    result: SlamResult
    """The filter's result (:func:`jaxslam.slam.run`; its ``closure`` is :attr:`closure`)."""
    closure: "LoopClosure | None"
    """The loop closure (:class:`jaxslam.graph.LoopClosure`: the pose graph, its loops, the
    optimised poses), or None where loops were not closed."""
    logodds: np.ndarray
    """(H, W) float16 log-odds of the final map: the map drawn again at the closed poses where the
    closure kept a loop, else the filter's best particle's map (what ``map.pgm`` holds, uncropped)."""
    hit_dist2: np.ndarray
    """(H, W) uint8: that map's likelihood field (squared distance to the nearest hit, in cells^2)."""
    grid: GridSpec
    """That map's grid (m per cell, origin in m), in the log's (world) frame."""
    trajectory: np.ndarray
    """(T, 3) float64 (m, m, rad) one pose per scan of the log, what ``trajectory.txt`` holds: the
    closure's optimised trajectory where loops were closed (searched), else the filter's."""
    refined: RefinedTrajectory | None
    """Every scan localised in the final map, then in the map its refined poses draw again
    (``poses`` (T, 3), world frame); None where the refinement was not asked for."""
    timings: dict
    """Seconds of the stages after the filter and the closure (theirs are in ``result.timings``
    and ``closure.timings``): ``closed_map`` (the final map: drawn again, or the filter's read
    out), and ``refinement`` where refined."""
    map_name: str
    """Which map :attr:`logodds` is (the figures' titles): ``"closed map"`` (drawn again at the
    closed poses, where the closure kept a loop) or ``"filter's map"`` (the best particle's)."""


def map_log(
    key: PRNGKeyArray,
    log: LaserLog,
    config: SlamConfig,
    params: SlamParams,
    settings: RunSettings = RunSettings(),
    *,
    close_loops: "bool | ClosureConfig" = True,
    refine: bool = True,
    progress: bool = True,
    chunk_size: int = 32,
    on_chunk=None,
    resume: RunProgress | None = None,
    prepared: tuple | None = None,
) -> MappedLog:
    """Map a log as ``jaxslam map`` does: the filter, the loop closure, the map drawn again at
    the closed poses and the refinement.

    Args:
      key, log, config, params, settings: as :func:`jaxslam.slam.run`.
      close_loops: True (the default) closes loops with :class:`jaxslam.graph.ClosureConfig`'s
        defaults; a ``ClosureConfig`` with its settings; False or None runs the filter alone.
      refine: localise every scan in the final map (:func:`jaxslam.refine.refine_in_rounds`).
      progress: tqdm bars for the filter, the closure and the refinement.
      chunk_size, on_chunk, resume, prepared: as :func:`jaxslam.slam.run` (checkpoints, resuming,
        a log prepared by the caller); an ``on_chunk`` that stops the run raises
        :class:`jaxslam.slam.RunInterrupted` before the closure.

    Returns:
      A :class:`MappedLog`.
    """
    closure_config = None
    if close_loops is True:
        # Imported here: jaxslam.graph (scipy.sparse) is 0.7 s of every command's start-up (measured).
        from jaxslam.graph import ClosureConfig

        closure_config = ClosureConfig()
    elif close_loops:
        closure_config = close_loops
    result = run(key, log, config, params, settings, chunk_size=chunk_size, progress=progress, on_chunk=on_chunk,
                 resume=resume, close_loops=closure_config, prepared=prepared)
    return finish_mapping(log, result, params, refine=refine, progress=progress)


def finish_mapping(log: LaserLog, result: SlamResult, params: SlamParams, refine: bool = True,
                   progress: bool = False) -> MappedLog:
    """The stages after the filter and its closure (``result.closure``, where it was closed):
    the map drawn again at the closed poses and, with ``refine``, the refinement in it. For a
    filter run elsewhere (:func:`jaxslam.slam.run_batch`, a notebook's :func:`jaxslam.slam.run`)."""
    t0 = time.perf_counter()
    closure = result.closure
    closed = closure is not None and closure.num_loops > 0
    if closed:
        logodds, field, grid = result.closed_map(log, params)
        local_grid = grid_to_world(grid, -result.frame_offset)
    else:
        logodds, field, local_grid = result.dense_map(local=True)
        grid = grid_to_world(local_grid, result.frame_offset)
    timings = {"closed_map": time.perf_counter() - t0}
    trajectory = result.trajectory if closure is None else closure.trajectory
    refined = None
    if refine:
        t0 = time.perf_counter()
        start = closure.trajectory if closed else result.trajectory
        refined = _refine(log, result, params, local_grid, field, start, progress)
        timings["refinement"] = time.perf_counter() - t0
    return MappedLog(result, closure, logodds, field, grid, trajectory, refined, timings,
                     "closed map" if closed else "filter's map")


def _refine(log, result, params, local_grid, field, start, progress: bool) -> RefinedTrajectory:
    """:func:`refine_in_rounds` of ``start`` (T, 3, world frame) in the map (``field`` on
    ``local_grid``), in the filter's local frame as the map was built; the result in the world frame."""
    # Where the loops found the odometry's heading the better one, its steps are trusted at
    # the noise the first round shows (refine.odometry_noise_scale).
    refined = refine_in_rounds(local_grid, field, result.to_local(start), log.ranges, log.sensor, params,
                               result.config, result.selection.indices, odometry=result.to_local(log.odometry),
                               trust_odometry=trusts_odometry(result.closure), progress=progress)
    return refined._replace(poses=result.to_world(refined.poses), matched_poses=result.to_world(refined.matched_poses))


def as_mapped(log: LaserLog, result, params: SlamParams, refined: RefinedTrajectory | None = None) -> MappedLog:
    """``result`` as a :class:`MappedLog`: itself if it is one; a :class:`~jaxslam.slam.SlamResult`
    (with its closure, if any) with the final map drawn (:func:`finish_mapping` without the
    refinement) and ``refined`` (world frame) as its refined trajectory."""
    if isinstance(result, MappedLog):
        return result
    return finish_mapping(log, result, params, refine=False)._replace(refined=refined)
