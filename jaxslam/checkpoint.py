"""Checkpoints of a SLAM run: written by :func:`jaxslam.slam.run`'s ``on_chunk``, read back for
its ``resume`` (``jaxslam map --checkpoint-every`` / ``--resume``)."""

from __future__ import annotations

import json
import zipfile

import numpy as np

from jaxslam.io.files import write_file_atomic
from jaxslam.maps import PagedMaps
from jaxslam.rbpf import SlamInfo, SlamState
from jaxslam.slam import RunProgress

CHECKPOINT_VERSION = 5  # 2: paged maps; 3: two-level page tables; 4: SlamInfo.num_slipped (the slip search);
# 5: SlamInfo.log_weights (each step's weights before resampling)


def save_checkpoint(path, progress: RunProgress, identity: dict) -> None:
    """Write ``progress`` (state, the infos so far, the steps done) and ``identity`` (JSON-able: what
    identifies the run, checked on resume) to the ``.npz`` file ``path`` atomically: into a temporary
    file in the same folder, flushed to disk, then renamed over ``path``."""
    info = progress.info() if callable(progress.info) else progress.info
    arrays = {"version": np.int64(CHECKPOINT_VERSION), "identity": np.array(json.dumps(identity, sort_keys=True)),
              "steps_done": np.int64(progress.steps_done), "num_steps": np.int64(progress.num_steps)}
    state = progress.state
    fields = {"poses": state.poses, "log_weights": state.log_weights, "step": state.step,
              **{f"maps.{name}": value for name, value in zip(PagedMaps._fields, state.maps)}}
    for name, value in fields.items():
        arrays[f"state.{name}"] = np.array(value)  # a copy: the device buffer may be donated next
    for name, value in zip(SlamInfo._fields, info):
        arrays[f"info.{name}"] = np.asarray(value)
    write_file_atomic(path, lambda f: np.savez(f, **arrays))


def load_checkpoint(path) -> tuple[RunProgress, dict]:
    """``(progress, identity)`` from a file of :func:`save_checkpoint` (NumPy arrays); ``ValueError``
    naming the file if it is not one."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["version"]) != CHECKPOINT_VERSION:
                raise ValueError(f"{path}: checkpoint version {int(z['version'])}, expected {CHECKPOINT_VERSION}")
            identity = json.loads(str(z["identity"]))
            maps = PagedMaps(*(z[f"state.maps.{name}"] for name in PagedMaps._fields))
            state = SlamState(z["state.poses"], z["state.log_weights"], maps, z["state.step"])
            info = SlamInfo(*(z[f"info.{name}"] for name in SlamInfo._fields))
            progress = RunProgress(int(z["steps_done"]), int(z["num_steps"]), state, info)
    except (KeyError, zipfile.BadZipFile, EOFError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a jaxslam checkpoint ({type(err).__name__}: {err})") from None
    return progress, identity
