"""Localization in a known map: Monte Carlo localization (:mod:`~jaxslam.localization.mcl`)
and localization with door-state estimation after Avots, Lim, Thibaux and Thrun
(:mod:`~jaxslam.localization.doors`), both with the beam model
(:mod:`~jaxslam.localization.beam_model`) on segment maps (:mod:`jaxslam.segment_map`); and
MCL in an occupancy grid with the endpoint model, recovery and KLD sampling
(:mod:`~jaxslam.localization.grid_mcl`, ``jaxslam localize``)."""

from jaxslam.localization import beam_model, doors, grid_mcl, mcl

__all__ = ["beam_model", "doors", "grid_mcl", "mcl"]
