"""Merge box-world results (folders or results.json files) into one folder.

    python experiments/box_world_merge.py OUT_DIR RESULTS [RESULTS ...] [--table noise] [--config FILE]

Writes OUT_DIR/results.json in ``box_world.py``'s format (runs already in it are kept), so that
``python experiments/box_world.py --table noise --out OUT_DIR`` finds the table's cells done and
only draws; and, for the table's cells, the figures, OUT_DIR/noise_scale.png and
OUT_DIR/noise_scale.md (method x odometry scale: successes / runs, rate ± binomial standard error).

Every input must be in ``box_world.py``'s format and have been written with the experiment file's
world and common settings, else it is refused. A (cell, seed) found in two inputs is taken from
the later one. From Python: :func:`merge_results`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import box_world as bw
from _runs import ResultStore, SettingsMismatch

from jaxslam.config import ConfigError


class MergeError(ValueError):
    """An input cannot be merged (other settings, unreadable)."""


def merge_results(paths, exp: dict | None = None, table: str = "noise") -> dict:
    """One results dict (``{"settings", "runs", "cells"}``, box_world.py's format, the world settings of
    ``table``) from results.json files or folders holding one."""
    exp = exp or bw.load_experiment()
    settings = bw.world_settings(exp, exp["tables"][table])
    cells: dict = {}
    runs: dict = {}
    for path in map(Path, paths):
        path = path / "results.json" if path.is_dir() else path
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise MergeError(f"{path}: cannot read: {err}") from None
        if not isinstance(data, dict) or "runs" not in data:
            raise MergeError(f"{path}: not a box_world.py results file (no 'runs')")
        if data.get("settings") != json.loads(json.dumps(settings)):
            raise MergeError(f"{path}: written with other settings: {data.get('settings')} (expected {settings})")
        new_cells, new_runs = data.get("cells", {}), data["runs"]
        for key, cell in new_cells.items():
            cells[key] = {k: cell[k] for k in ("method", "settings", "N", "odometry_scale")}
        for run in new_runs:
            earlier = runs.get((run["cell"], run["seed"]))
            if earlier is not None and earlier["ra"] != run["ra"]:
                print(f"{path}: seed {run['seed']} of {cells[run['cell']]['method']} N={cells[run['cell']]['N']} "
                      f"scale {cells[run['cell']]['odometry_scale']:g} replaces a run with another RA", file=sys.stderr)
            runs[(run["cell"], run["seed"])] = run
    return {"settings": settings, "runs": list(runs.values()), "cells": cells}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="the folder to write (its results.json's runs are kept)")
    ap.add_argument("inputs", nargs="+", help="results.json files or folders holding one")
    ap.add_argument("--config", default=str(bw.DEFAULT_CONFIG), help="the experiment file")
    ap.add_argument("--table", default="noise", help="the table whose cells the figures and noise_scale.md show")
    args = ap.parse_args(argv)
    out = Path(args.out)
    try:
        exp = bw.load_experiment(args.config)
        table = exp["tables"][args.table]
        merged = merge_results(args.inputs, exp, args.table)
        store = ResultStore(out / "results.json", merged["settings"], key=lambda r: (r["cell"], r["seed"]))
    except KeyError as err:
        print(f"box_world_merge.py: no table {err} in {args.config}", file=sys.stderr)
        return 2
    except (ConfigError, MergeError, SettingsMismatch, OSError, json.JSONDecodeError) as err:
        print(f"box_world_merge.py: {err}", file=sys.stderr)
        return 2
    cells = store.sections.setdefault("cells", {})
    for key, cell in merged["cells"].items():
        cells.setdefault(key, {}).update(cell)
    store.add(*merged["runs"], cells=cells)
    shown = bw.table_cells(exp, table, table["methods"], table.get("set", {}))
    bw.write_summaries(out, store, shown, exp["success_ra"])
    bw.print_table(shown, store.runs, exp["success_ra"])
    print(f"wrote {out / 'results.json'} ({len(store.runs)} runs in {len(cells)} cells)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
