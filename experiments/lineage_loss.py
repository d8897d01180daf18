"""Why a run's particles lose their histories: chance (weights that do not last) or selection
(the same lineages winning), from the ``steps.npz`` of finished runs.

For each run folder (``jaxslam map`` or ``experiments/datasets.py`` output):

* ``increment_spread``: the median over steps of the log-weight increments' standard deviation
  over the particles (nats); ``persistence``: the median correlation of a stretch's first half
  with its second (:func:`jaxslam.diagnose.weight_persistence`);
* ``pair_coalescence``: the recorded rate at which lineages merge, per step
  (:func:`jaxslam.diagnose.pair_coalescence`); ``replayed``: the same from the recorded increments
  replayed with systematic resampling at ESS < N/2 (a check of the replay); ``shuffled``: the
  replay with each step's increments dealt to the particles at random (the same spread, nothing
  lasts); ``drift_share`` = shuffled / replayed: how much of the merging chance alone gives;
* ``lag_steps``: the final particles' common ancestor, in steps before the end; ``neutral``: the
  same resamplings with the lucky particles drawn afresh at every step
  (:func:`jaxslam.diagnose.neutral_coalescence_lags`), median and the recorded lag's quantile.
* ``lineages_back``: how many distinct histories the particles still held 25, 50, 100 and 200
  steps back, the median over the run's steps (:func:`jaxslam.diagnose.lineages_back`): the
  alternatives carried at every step, where ``lag_steps`` is the end's alone;
  ``neutral_lineages_back``: the same of the relabelled resamplings (the median over
  ``NEUTRAL_LINEAGE_DRAWS``): fewer recorded than neutral is selection; ``lineages_curve``: both
  at ``CURVE_LAGS``, drawn against the lag by ``--figure``, a line a run, coloured by N.

And, independent of any run, the pure-drift rate of merging against the resampling threshold
(``--thresholds``): i.i.d. increments of a given spread, systematic resampling at ESS < r N.

    python experiments/lineage_loss.py RUN_DIR [RUN_DIR ...] --out OUT/lineage_loss.json
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.diagnose import (LINEAGE_LAGS, coalescence_lag, lineages_back, neutral_coalescence_lags,
                              pair_coalescence, read_step_record, relabelled_parents, weight_persistence)
from jaxslam.resampling import resample_if_needed

REPLAYS = 20
"""Replays of a run's increments per variant (kept and shuffled)."""


@partial(jax.jit, static_argnames=("shuffle",))
def _replays(keys, increments, threshold, shuffle: bool):
    """(R,) pair coalescence per step of R replays (one key each) of ``increments`` (S, N)."""
    steps, n = increments.shape

    def replay(key):
        def step(log_weights, inputs):
            key_t, increment = inputs
            key_deal, key_resample = jax.random.split(key_t)
            if shuffle:
                increment = jax.random.permutation(key_deal, increment)
            # The filter's own rule and resampler: systematic, where the ESS < threshold N.
            ancestors, log_weights, resampled = resample_if_needed(key_resample, log_weights + increment, threshold)
            counts = jnp.zeros(n).at[ancestors].add(1.0)
            return log_weights, jnp.where(resampled, jnp.sum(counts * (counts - 1)) / (n * (n - 1)), 0.0)

        _, merged = jax.lax.scan(step, jnp.full((n,), -jnp.log(n)), (jax.random.split(key, steps), increments))
        return merged.mean()

    return jax.vmap(replay)(keys)


def replay_merging(increments: np.ndarray, seed: int, shuffle: bool, threshold: float = 0.5,
                   replays: int = REPLAYS) -> float:
    """Pair coalescence per step of a filter whose log-weights take ``increments`` (S, N) step by
    step and resample systematically when the ESS falls below ``threshold`` N (the mean of
    ``replays`` replays); with ``shuffle`` each step's increments are dealt to the particles in a
    random order. A particle of weight zero (NaN increment) gets -50 nats."""
    keys = jax.random.split(jax.random.key(seed), replays)
    increments = jnp.asarray(np.nan_to_num(increments, nan=-50.0), jnp.float32)
    return float(jnp.mean(_replays(keys, increments, jnp.float32(threshold), shuffle)))


NEUTRAL_LINEAGE_DRAWS = 20
"""Relabelled copies of a run's resamplings behind ``neutral_lineages_back`` (each gives a median
over hundreds of steps, so a few draws settle it)."""

CURVE_LAGS = (1, 2, 5, 10, 25, 50, 100, 200, 300, 400, 600, 800)
"""The lags (steps) of ``lineages_curve`` and ``--figure``, with ``diagnose.LINEAGE_LAGS``."""


def run_figures(run_dir: Path, seed: int = 0) -> dict:
    """The module's figures for one run folder."""
    record = read_step_record(run_dir)
    ancestors, resampled = np.asarray(record["ancestors"]), np.asarray(record["resampled"])
    n = ancestors.shape[1]
    persistence = weight_persistence(record["log_weights"], ancestors, resampled)
    increments = persistence["increments"]
    replayed = replay_merging(increments, seed, False)
    shuffled = replay_merging(increments, seed + 1, True)
    neutral = neutral_coalescence_lags(ancestors, seed=seed)
    lag = coalescence_lag(ancestors)
    rng = np.random.default_rng(seed)
    lags = sorted(set(CURVE_LAGS) | set(LINEAGE_LAGS))
    held = lineages_back(ancestors, lags)
    draws = [lineages_back(relabelled_parents(ancestors, rng), lags) for _ in range(NEUTRAL_LINEAGE_DRAWS)]
    neutral_held = {k: float(np.median([draw[k] for draw in draws])) if held[k] is not None else None for k in held}
    timestamps = np.asarray(record["timestamp"])
    errors = run_dir / "errors.json"  # experiments/datasets.py's relation error, where it scored the run
    relation_error = json.loads(errors.read_text()).get("trans_mean") if errors.is_file() else None
    return {"run": str(run_dir), "relation_error": relation_error, "num_particles": int(n),
            "steps": int(ancestors.shape[0]),
            "seconds_per_step": float(np.median(np.diff(timestamps))),
            "resamplings": int(resampled.sum()),
            "increment_spread": persistence["median_increment_spread"],
            "persistence": persistence["median_correlation"],
            "pair_coalescence": float(np.mean(pair_coalescence(ancestors))),
            "replayed": replayed, "shuffled": shuffled, "drift_share": shuffled / replayed if replayed else None,
            "lag_steps": lag, "neutral_lag_median": float(np.median(neutral)),
            "neutral_lag_quantile": float(np.mean(neutral <= lag)),
            # How many histories the particles still held that many steps back, the median over the run's
            # steps; and the same resamplings relabelled (neutral drift), the median over the draws.
            "lineages_back": {str(k): held[str(k)] for k in LINEAGE_LAGS},
            "neutral_lineages_back": {str(k): neutral_held[str(k)] for k in LINEAGE_LAGS},
            "lineages_curve": {"lags": lags, "held": list(held.values()),
                               "neutral": list(neutral_held.values())}}


def drift_against_threshold(spread: float, thresholds, n: int = 30, steps: int = 20_000, seed: int = 0) -> dict:
    """Pure drift: pair coalescence per step for i.i.d. N(0, spread^2) increments, against the
    resampling threshold (the same increments for every threshold)."""
    increments = np.random.default_rng(seed).normal(0.0, spread, (steps, n))
    return {str(threshold): replay_merging(increments, seed, False, threshold) for threshold in thresholds}


def plot_lineages(runs: list[dict], path: Path) -> None:
    """Each run's ``lineages_curve``: the histories held (solid) and neutral drift's (dashed)
    against the steps back, log-log, coloured by the number of particles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted({r["num_particles"] for r in runs})
    colours = {n: plt.cm.viridis(i / max(len(sizes) - 1, 1) * 0.8) for i, n in enumerate(sizes)}
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for r in runs:
        curve = r["lineages_curve"]
        lags = [k for k, v in zip(curve["lags"], curve["held"]) if v is not None]
        colour = colours[r["num_particles"]]
        ax.plot(lags, curve["held"][:len(lags)], color=colour, lw=1, alpha=0.8)
        ax.plot(lags, curve["neutral"][:len(lags)], color=colour, lw=1, ls="--", alpha=0.5)
    for n in sizes:
        ax.plot([], [], color=colours[n], label=f"N = {n}, held")
    ax.plot([], [], color="grey", ls="--", label="the same resamplings relabelled (neutral)")
    ax.set(xscale="log", yscale="log", xlabel="steps back", ylabel="distinct histories held (median over steps)",
           title="How far back the particles' alternatives reach")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders holding steps.npz")
    ap.add_argument("--out", type=Path, required=True, help="the JSON to write")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.25, 0.5, 0.75, 0.9])
    ap.add_argument("--spreads", type=float, nargs="+", default=[0.12, 0.18, 0.25])
    ap.add_argument("--figure", type=Path, help="also draw the histories held against the steps back (a PNG)")
    args = ap.parse_args(argv)
    missing = [str(r) for r in args.runs if not (r / "steps.npz").is_file()]
    if missing:
        print(f"lineage_loss.py: no steps.npz in {', '.join(missing)}", file=sys.stderr)
        return 2
    if args.figure is not None and args.figure.is_dir():
        print(f"lineage_loss.py: --figure {args.figure} is a folder; give the PNG's path", file=sys.stderr)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from tqdm.auto import tqdm

    runs = [run_figures(r) for r in tqdm(args.runs, desc="runs", unit="run")]
    drift = {str(s): drift_against_threshold(s, args.thresholds) for s in args.spreads}
    args.out.write_text(json.dumps({"runs": runs, "pure_drift_pair_coalescence": drift}, indent=1) + "\n")
    for r in runs:
        print(f"{r['run']}: spread {r['increment_spread']:.3f} nats, persistence {r['persistence']:.2f}, merging "
              f"{r['pair_coalescence'] * 1e3:.2f}e-3 a step (replayed {r['replayed'] * 1e3:.2f}e-3, shuffled "
              f"{r['shuffled'] * 1e3:.2f}e-3: drift {r['drift_share']:.2f}), lag {r['lag_steps']} steps against "
              f"{r['neutral_lag_median']:.0f} neutral (quantile {r['neutral_lag_quantile']:.2f}); histories held "
              + ", ".join(f"{v:.0f} ({r['neutral_lineages_back'][k]:.0f} neutral) at {k}"
                          for k, v in r["lineages_back"].items() if v is not None) + " steps back")
    if args.figure is not None:
        plot_lineages(runs, args.figure)
        print(f"figure: {args.figure}")
    for spread, rates in drift.items():
        print(f"pure drift, spread {spread}: " + ", ".join(f"r = {k}: {v * 1e3:.2f}e-3" for k, v in rates.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
