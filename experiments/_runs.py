"""The resume/cache helper shared by the experiments (``box_world.py``, ``datasets.py``).

A :class:`ResultStore` is one folder's ``results.json``: the settings it was written with,
a list of run records (one per finished run, told apart by ``key(run)``) and any summary
sections. It refuses a folder written with other settings (:class:`SettingsMismatch`), says
which runs are done, and rewrites the file atomically after every added run, keeping the
runs of earlier calls. So an experiment can be stopped and restarted, and a later call into
the same folder adds its runs beside the earlier ones. :func:`closure_settings` reads the closure
experiments' ``--set NAME=VALUE`` (``closure_stress.py``, ``loop_closure.py``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Hashable

from jaxslam.io.files import write_file_atomic


class SettingsMismatch(Exception):
    """The folder's results.json was written with other settings."""


def _plain(value: Any) -> Any:
    """``value`` as it reads back from JSON (tuples become lists, ...), for comparisons."""
    return json.loads(json.dumps(value))


def write_json(path: Path, data: Any):
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, then ``os.replace``
    (an interrupted write never leaves a broken file)."""
    write_file_atomic(path, json.dumps(data, indent=2))


class ResultStore:
    """``path`` (a results.json): ``{"settings": ..., "runs": [...], <sections>...}``.

    Args:
      path: the results.json (its folder is created on the first write).
      settings: what the runs depend on beyond their own record; a stored file with other
        settings raises :class:`SettingsMismatch`.
      key: a run record's identity (e.g. ``lambda r: (r["cell"], r["seed"])``); adding a run
        with the key of a stored one replaces it.
    """

    def __init__(self, path, settings: dict, key: Callable[[dict], Hashable]):
        self.path = Path(path)
        self.settings = _plain(settings)
        self.key = key
        self.sections: dict = {}
        self.runs: list[dict] = []
        if self.path.is_file():
            data = json.loads(self.path.read_text())
            if data.get("settings") != self.settings:
                raise SettingsMismatch(
                    f"{self.path} was written with other settings; its runs would be mixed with these: "
                    f"choose another folder.\n  stored:    {json.dumps(data.get('settings'), sort_keys=True)}"
                    f"\n  requested: {json.dumps(self.settings, sort_keys=True)}")
            self.runs = list(data.get("runs", []))
            self.sections = {k: v for k, v in data.items() if k not in ("settings", "runs")}
        self._index = {self.key(r): i for i, r in enumerate(self.runs)}

    def get(self, key: Hashable) -> dict | None:
        """The stored run with this key, or None."""
        i = self._index.get(key)
        return None if i is None else self.runs[i]

    def done(self, key: Hashable) -> bool:
        return key in self._index

    def add(self, *runs: dict, **sections):
        """Store ``runs`` (each replacing a stored run with its key), update ``sections``, write the file."""
        for run in runs:
            k = self.key(run)
            if k in self._index:
                self.runs[self._index[k]] = run
            else:
                self._index[k] = len(self.runs)
                self.runs.append(run)
        self.write(**sections)

    def write(self, **sections):
        """Update the summary ``sections`` and rewrite the file atomically."""
        self.sections.update(sections)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, {"settings": self.settings, "runs": self.runs, **self.sections})


def gather_json(value: Any) -> list:
    """Every process's ``value`` (JSON-able), in process order: ``[value]`` in a single process;
    under ``jax.distributed``, a collective that every process must call at the same point."""
    import jax

    if jax.process_count() == 1:
        return [_plain(value)]
    import numpy as np
    from jax.experimental import multihost_utils

    data = np.frombuffer(json.dumps(value).encode(), np.uint8)
    sizes = np.asarray(multihost_utils.process_allgather(np.int32(data.size)))
    padded = np.zeros(int(sizes.max()), np.uint8)
    padded[:data.size] = data
    every = np.asarray(multihost_utils.process_allgather(padded))
    return [json.loads(bytes(every[p, :sizes[p]]).decode()) for p in range(sizes.size)]


def closure_settings(items: list[str]) -> dict:
    """``{field: value}`` of ``NAME=VALUE`` texts naming :class:`jaxslam.graph.ClosureConfig`
    fields (``--set`` of the closure experiments), each value of its field's type; ValueError
    naming the text otherwise (no field of that name, or a value the type refuses)."""
    import dataclasses

    from jaxslam.graph import ClosureConfig

    defaults = ClosureConfig()
    names = [f.name for f in dataclasses.fields(ClosureConfig)]
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in names:
            raise ValueError(f"--set {item}: {name!r} is no ClosureConfig field ({', '.join(names)})")
        default = getattr(defaults, name)
        try:
            out[name] = value if isinstance(default, str) else type(default)(value)
        except ValueError:
            raise ValueError(f"--set {item}: {value!r} is no {type(default).__name__}") from None
    dataclasses.replace(defaults, **out)  # ClosureConfig's own checks, before any work
    return out
