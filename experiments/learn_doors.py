"""Learning the doors' transition probabilities from a simulated patrol with the door filter's
log-likelihood (Avots et al.'s hybrid filter, :mod:`jaxslam.localization.doors`).

The patrol (:func:`jaxslam.sim.door_worlds.patrol_doors_scenario`: ten round trips along a
corridor with six doors, about 1,900 scans) draws every door's state from a Markov chain: per
scan a closed door opens with probability 0.01 and an open one closes with 0.01. The filter
knows the walls and doors, not their states; its transition model is two numbers shared by
the doors, p(open | closed) and p(closed | open). Starting from ``--start`` (default 0.04 and
0.0025: four times too high and four times too low), Adam (:func:`jaxslam.learning.fit`, logit
coordinates) climbs ``doors.filter``'s log-likelihood estimate with the untempered beam model
(likelihood gain 1). The door beliefs are exact per particle (Rao-Blackwellised), so the
gradient in the transition probabilities is mostly analytic; the score terms of the
resamplings carry the rest. Also reported: the complete-data estimate (transition counts of
the true door states, which no filter sees), the best any estimator of this log could do.

    python experiments/learn_doors.py --steps 40 --out docs/results/learn_doors.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

NAMES = ("p_open_closed", "p_closed_open")


def complete_data_estimate(true_open: np.ndarray) -> dict[str, float]:
    """Transition counts of (T, K) true door states: the maximum-likelihood estimate had every
    door been observed at every scan."""
    before, after = true_open[:-1], true_open[1:]
    return {"p_open_closed": float((~before & after).sum() / (~before).sum()),
            "p_closed_open": float((before & ~after).sum() / before.sum()),
            "transitions": int((before != after).sum())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--round-trips", type=int, default=10)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--learning-rate", type=float, default=0.1)
    parser.add_argument("--gain", type=float, default=1.0, help="likelihood gain during the fit (1: untempered)")
    parser.add_argument("--start", type=float, nargs=2, default=[0.04, 0.0025],
                        metavar=("P_OPEN_CLOSED", "P_CLOSED_OPEN"))
    parser.add_argument("--truth", type=float, nargs=2, default=[0.01, 0.01],
                        metavar=("P_OPEN_CLOSED", "P_CLOSED_OPEN"), help="the simulation's transition probabilities")
    parser.add_argument("--out", default="results/learn_doors.json")
    args = parser.parse_args(argv)
    for value in (*args.start, *args.truth):
        if not 0.0 < value < 1.0:
            parser.error(f"transition probabilities must be in (0, 1), got {value}")

    import jax
    import jax.numpy as jnp

    from jaxslam.learning import UNIT_INTERVAL, fit
    from jaxslam.localization import doors, mcl
    from jaxslam.localization.beam_model import make_beam_model_params
    from jaxslam.sim.door_worlds import patrol_doors_scenario

    scenario = patrol_doors_scenario(jax.random.key(0), num_round_trips=args.round_trips,
                                     p_open_closed=args.truth[0], p_closed_open=args.truth[1])
    door_map, sensor = scenario.door_map, scenario.log.sensor
    config = doors.DoorConfig(mcl.MclConfig(num_particles=args.particles, beam_stride=2))
    base = doors.make_params(door_map, beam=make_beam_model_params(sigma_hit=0.2), likelihood_gain=args.gain)
    inputs = mcl.log_inputs(scenario.log)
    regions = jnp.asarray(scenario.start_regions)
    num_doors = door_map.num_doors

    def with_transitions(p):
        return base._replace(p_open_open=jnp.full((num_doors,), 1.0 - p["p_closed_open"]),
                             p_open_closed=jnp.full((num_doors,), p["p_open_closed"]))

    def objective(key, p):
        k_init, k_run = jax.random.split(key)
        start = mcl.init_global(k_init, regions, config.mcl, tuple(scenario.heading_range))
        out = doors.filter(k_run, doors.init(start, door_map), inputs, door_map, sensor, with_transitions(p), config)
        return out.marginal_loglik

    start = {"p_open_closed": jnp.float32(args.start[0]), "p_closed_open": jnp.float32(args.start[1])}
    result = fit(jax.random.key(1), objective, start, num_steps=args.steps, learning_rate=args.learning_rate,
                 transforms={name: UNIT_INTERVAL for name in NAMES})
    truth = dict(zip(NAMES, args.truth))
    final = {name: float(result.history[name][-1]) for name in NAMES}
    # The learned value: the mean of the last quarter of the steps (Adam's iterates jitter
    # around the maximum by about one learning rate in logit).
    tail = max(1, args.steps // 4)
    learned = {name: float(np.mean(result.history[name][-tail:])) for name in NAMES}
    record = {"args": vars(args), "truth": truth, "complete_data": complete_data_estimate(scenario.true_door_open),
              "start": dict(zip(NAMES, args.start)), "final": final, "learned_tail_mean": learned,
              "history": {k: v.tolist() for k, v in result.history.items()}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2))
    for name in NAMES:
        print(f"{name}: truth {truth[name]:.4f}, complete-data {record['complete_data'][name]:.4f}, "
              f"start {record['start'][name]:.4f}, learned {learned[name]:.4f} ({learned[name] / truth[name]:.2f} x truth)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
