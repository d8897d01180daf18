"""Merge box-world results (folders or results.json files, new or old format) into one folder.

    python experiments/box_world_merge.py OUT_DIR RESULTS [RESULTS ...] [--table noise] [--config FILE]

Writes OUT_DIR/results.json in ``box_world.py``'s format (runs already in it are kept), so that
``python experiments/box_world.py --table noise --out OUT_DIR`` finds the table's cells done and
only draws; and, for the table's cells, the figures, OUT_DIR/noise_scale.png and
OUT_DIR/noise_scale.md (method x odometry scale: successes / runs, rate ± binomial standard error).

Old-format files (``box_world.py`` before box_world.json: cells keyed "OP | N=50" with their runs
inside) are converted: the label names the method (:data:`OLD_LABELS`; other labels are skipped
with a warning), ``settings.world_odometry_scale`` gives the scale (default 1). Every input must
have been written with the experiment file's world and common settings, else it is refused. A
(cell, seed) found in two inputs is taken from the later one. From Python: :func:`merge_results`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import box_world as bw
from _runs import ResultStore, SettingsMismatch

from jaxslam.config import ConfigError

OLD_LABELS = {
    "OP": "OP", "SMP": "SMP", "LP a=0 L=100 k=5": "LP a=0", "LP a=0.5 L=100 k=5": "LP",
    "LP a=0.5 L=50 k=3": "LP L=50 k=3", "LP-SM a=0.5 L=100 k=5": "LP-SM", "LP a=0.5 c=0 L=100 k=5": "LP c=0",
    "LP-SM a=0.5 c=0 L=100 k=5": "LP-SM c=0",
}
"""Old-format method labels -> box_world.json's method names."""


class MergeError(ValueError):
    """An input cannot be merged (other settings, unreadable)."""


def _old_settings_problems(settings: dict, exp: dict) -> list[str]:
    """Where an old-format file's settings differ from the experiment file's."""
    expected = {
        "motion_scale": exp["motion_scale"], "rotation_weight": exp["rotation_weight"],
        "success_ra": exp["success_ra"], "scenario": {}, "quick": False, "set": [], "localizers": None,
        "horizon": None, "likelihood_field": "endpoints", "lookahead_weight": "filter",
        **{k: exp["common"][k] for k in ("beam_stride", "linear_update", "angular_update", "match_lookup")},
    }
    return [f"{k} = {settings[k]!r} (expected {v!r})" for k, v in expected.items()
            if k in settings and settings[k] != v and not (v == {} and settings[k] is None)]


def convert_old(data: dict, exp: dict, source: str = "old results") -> tuple[dict, list[dict]]:
    """An old-format results dict -> (cells, runs) of box_world.py's format."""
    problems = _old_settings_problems(data.get("settings", {}), exp)
    if problems:
        raise MergeError(f"{source}: written with other settings: {'; '.join(problems)}")
    scale = float(data.get("settings", {}).get("world_odometry_scale", 1.0))
    cells, runs = {}, []
    for label, cell in data["cells"].items():
        name = OLD_LABELS.get(cell.get("method", label.split(" | ")[0]))
        if name is None:
            print(f"{source}: skipping cell {label!r} (a label box_world.json has no method for)", file=sys.stderr)
            continue
        record = {"method": name, **bw.cell_record(bw.method_settings(exp, name), cell["N"], scale)}
        key = bw.cell_key(record)
        cells[key] = record
        runs += [{"cell": key, **{f: r[f] for f in bw.RUN_FIELDS if f in r}} for r in cell["runs"]]
    return cells, runs


def merge_results(paths, exp: dict | None = None, table: str = "noise") -> dict:
    """One results dict (``{"settings", "runs", "cells"}``, box_world.py's format, the world settings of
    ``table``) from results.json files or folders holding one, old format or new."""
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
        if "runs" in data:  # box_world.py's format
            if data.get("settings") != json.loads(json.dumps(settings)):
                raise MergeError(f"{path}: written with other settings: {data.get('settings')} (expected {settings})")
            new_cells, new_runs = data.get("cells", {}), data["runs"]
        else:
            new_cells, new_runs = convert_old(data, exp, str(path))
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
    ap.add_argument("inputs", nargs="+", help="results.json files or folders holding one (old or new format)")
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
