"""The proposals' step: its sequential depth, its cost per update and its beam evaluations per second.

On the simulated office (``jaxslam demo``'s settings, the library's defaults otherwise), for each
proposal: the compiled RBPF step's loops (every ``scan`` / ``while`` in its jaxpr with its trip
count: the rounds that must run one after another), the wall time per update of ``rbpf.filter``
over the log's first scans (compiled once, median of repeats), and the proposal's beam
evaluations per second (pose evaluations a particle makes per step, times beams, times particles,
over that time; the insertion's cost is in the time too, so this is a lower bound).

    python benchmarks/bench_proposals.py --out results/bench_proposals.json
    python benchmarks/bench_proposals.py --proposal op smp lp --also free_space_samples=200

Run it in two checkouts on one machine, one after the other, for a before/after ratio. ``--also
NAME=VALUE ...`` times every proposal a second time with those settings in the same run and
reports the ratio of the two times per update (the office's 10 m insertion range at 5 cm is 200
cells: ``free_space_samples=200`` checks every inserted beam's free path).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path


def loops(jaxpr) -> list[tuple[str, int]]:
    """Every ``scan`` and ``while`` in ``jaxpr`` (nested ones included) with its trip count
    (a while's is unknown: -1)."""
    found = []
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "scan":
            found.append(("scan", int(eqn.params["length"])))
        elif name == "while":
            found.append(("while", -1))
        for value in eqn.params.values():
            inner = getattr(value, "jaxpr", None)
            if inner is not None and hasattr(inner, "eqns"):
                found += loops(inner)
            elif hasattr(value, "eqns"):
                found += loops(value)
    return found


def pose_evaluations(config) -> int:
    """Poses a particle scores per step (the proposal's likelihood evaluations)."""
    if config.proposal == "op":
        return 1
    if hasattr(config, "window_cells"):  # the window posterior
        # Each mode splits one seed cell at the first level, its kept cells at the later ones.
        per_mode, cells = 0, 1
        for _ in range(config.window_levels):
            per_mode += 8 * cells
            cells = min(config.window_keep, 8 * cells)
        search = config.window_cells**3 + config.window_modes * per_mode
        polish_and_fit = config.window_modes * (9 + 27) + 1  # the polish, the stencils, the match score
        base = search + polish_and_fit
    else:  # the hill climber of earlier versions: a start, six moves a round, the stencil, the score
        base = 1 + 6 * config.match_iterations + 27 + 1
    # The slip search's test: two window posteriors of one particle a step, shared by all
    # (jaxslam.slip_search.slip_log_odds; the second pass at the steps where it fires is not counted).
    from jaxslam.slip_search import searches_window

    slip_test = 2 * base / config.num_particles if searches_window(config) else 0
    if config.proposal == "lp":
        return round(base + slip_test + config.num_localizers * (2 + config.horizon))
    return round(base + slip_test)


def time_proposal(log, proposal: str, assignments: dict, args) -> dict:
    """One proposal's row: the step's loops, its seconds per update (median of repeats, compiled
    once) and its beam evaluations per second, with ``assignments`` over the demo's settings."""
    import jax
    import numpy as np

    from jaxslam import rbpf
    from jaxslam.cli import DEMO_DEFAULTS
    from jaxslam.config import build_setup

    config, settings, params = build_setup({**DEMO_DEFAULTS, "proposal": proposal,
                                            "num_particles": args.particles, **assignments})
    prepared, selection, _ = rbpf.prepare(log, config, settings)
    steps = int(selection.indices.size - 1)
    one_step = jax.tree.map(lambda a: a[0], prepared.inputs)
    state = rbpf.init(jax.random.key(0), prepared.first_ranges, prepared.sensor, params, config,
                      prepared.initial_pose)
    jaxpr = jax.make_jaxpr(lambda k, s, i: rbpf.step(k, s, i, prepared.sensor, params, config))(
        jax.random.key(1), state, one_step)
    step_loops = loops(jaxpr.jaxpr)
    run = jax.jit(lambda key: rbpf.filter(key, prepared, params, config).marginal_loglik)
    t0 = time.perf_counter()
    jax.block_until_ready(run(jax.random.key(0)))
    compile_s = time.perf_counter() - t0
    times = []
    for r in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(jax.random.key(1 + r)))
        times.append(time.perf_counter() - t0)
    per_update = float(np.median(times)) / steps
    beams = int(np.ceil(prepared.inputs.ranges.shape[-1] / config.beam_stride))
    evaluations = pose_evaluations(config)
    row = {"proposal": proposal, "settings": assignments, "particles": args.particles, "steps": steps,
           "step_loops": step_loops, "sequential_rounds": sum(max(n, 1) for _, n in step_loops),
           "seconds_per_update": per_update, "pose_evaluations_per_particle": evaluations,
           "beam_evaluations_per_second": evaluations * beams * args.particles / per_update,
           "compile_s": compile_s}
    print(f"{proposal} {assignments or ''}: {steps} updates, {per_update * 1e3:.1f} ms each; loops in the step "
          f"{step_loops}; {evaluations} poses a particle, {row['beam_evaluations_per_second']:.3g} beam evaluations/s",
          flush=True)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--proposal", nargs="+", default=["smp", "lp"],
                        help="registered proposals (jaxslam.proposals.PROPOSALS)")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--scans", type=int, default=120, help="scans of the simulated office")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--also", nargs="+", default=[], metavar="NAME=VALUE",
                        help="time every proposal again with these build_setup settings; report the ratio")
    parser.add_argument("--out", default="results/bench_proposals.json")
    args = parser.parse_args(argv)

    import jax
    import numpy as np

    from jaxslam.cli import parse_assignments
    from jaxslam.sim import office_scenario

    also = parse_assignments(args.also)

    log = office_scenario(jax.random.key(0)).log
    log = log.subset(np.arange(min(args.scans, log.num_scans)))
    rows = {}
    variants = [("defaults", {})] + ([("also", also)] if also else [])
    for proposal in args.proposal:
        for variant, assignments in variants:
            name = proposal if variant == "defaults" else f"{proposal} with {' '.join(args.also)}"
            rows[name] = time_proposal(log, proposal, assignments, args)
        if also:
            ratio = rows[name]["seconds_per_update"] / rows[proposal]["seconds_per_update"]
            rows[name]["time_ratio_to_defaults"] = ratio
            print(f"{proposal}: {ratio:.2f}x the time per update with {' '.join(args.also)}", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": platform.platform(), "jax": jax.__version__, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
