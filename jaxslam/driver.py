"""The one host-side driver of long runs: a jitted function applied chunk by chunk.

Every long computation in the package (a filter over a log, localising every scan of a
log, simulating a log's scans) has a per-item step and many items. Compiling one call per
item is slow and one call for all of them shows no progress and holds every intermediate:
:func:`run_in_chunks` cuts the items into fixed-size chunks (the last one padded, so the
chunk function compiles once), threads an optional carry through them, collects each
chunk's output on the host and shows a tqdm bar.
"""

from __future__ import annotations

import time
from typing import Any, Callable, NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

ChunkFn = Callable[[Any, Any, np.ndarray], tuple[Any, Any]]
"""``chunk_fn(carry, xs_chunk, valid_chunk) -> (carry, outputs_chunk)``; ``valid_chunk`` (C,)
is False on the padding items past the end (their outputs are dropped)."""


class ChunkedRun(NamedTuple):
    """What :func:`run_in_chunks` returns."""

    carry: Any
    """The carry after the last chunk."""
    outputs: Any
    """Every chunk's outputs concatenated along the leading axis, padding removed (NumPy)."""
    first_chunk_seconds: float
    """Wall time of the first chunk (compilation included)."""
    num_done: int = -1
    """Items processed: ``num_items``, or fewer when ``on_chunk`` asked to stop (a multiple of
    ``chunk_size``); ``outputs`` then holds only those."""


ChunkCallback = Callable[[int, Any, Callable[[], Any]], bool]
"""``on_chunk(chunk_index, carry, outputs_so_far) -> stop``, called after each chunk on the host:
``chunk_index`` counts from 0, ``carry`` is the carry after it, ``outputs_so_far()`` returns the
outputs of the chunks done (concatenated, padding removed; computed only when called). A true
return value stops the run at this chunk boundary."""


def pad_items(tree: Any, total: int) -> Any:
    """Every leaf of ``tree`` cut or padded along its leading axis to ``total`` items. Padding
    repeats the last item (PRNG key arrays included); an empty leaf is padded with zeros."""

    def pad(a):
        n = a.shape[0]
        if n >= total:
            return a[:total]
        if n == 0:
            return np.zeros((total,) + a.shape[1:], a.dtype)
        return a[np.minimum(np.arange(total), n - 1)]

    return jax.tree.map(pad, tree)


def run_in_chunks(
    chunk_fn: ChunkFn,
    xs: Any,
    num_items: int,
    chunk_size: int,
    carry: Any = None,
    *,
    progress: bool = False,
    desc: str | None = None,
    unit: str = "item",
    on_chunk: ChunkCallback | None = None,
) -> ChunkedRun:
    """Apply ``chunk_fn`` to ``num_items`` items of ``xs`` (leading axis) in chunks of
    ``chunk_size``.

    Args:
      chunk_fn: see :data:`ChunkFn`; typically a jitted ``lax.scan`` (with a carry) or a vmap
        (carry None).
      xs: a pytree of arrays with a leading item axis of at least ``num_items`` entries
        (more are ignored; an array with fewer must be empty or is padded by its last item).
      num_items: how many items to process.
      chunk_size: items per call (static for the chunk function: one compilation).
      carry: the initial carry (None for a map).
      progress: show a tqdm bar (on stderr; "compiling..." beside it until the first chunk is
        done); desc, unit: its label.
      on_chunk: see :data:`ChunkCallback` (e.g. to write a checkpoint or to stop on a signal;
        the carry may be donated by the next chunk, so copy what must outlive the call).

    Returns:
      A :class:`ChunkedRun`.
    """
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    num_chunks = max(1, -(-num_items // chunk_size))
    padded = pad_items(xs, num_chunks * chunk_size)
    valid = np.arange(num_chunks * chunk_size) < num_items
    outputs = []
    first_chunk_seconds = 0.0

    def stack(done):
        return jax.tree.map(lambda *parts: np.concatenate(parts)[:done], *outputs)

    num_done = num_items
    with tqdm(total=num_items, desc=desc, unit=unit, disable=not progress) as bar:
        for index, start in enumerate(range(0, num_chunks * chunk_size, chunk_size)):
            sl = slice(start, start + chunk_size)
            if index == 0:  # the first call compiles: say so, rather than sit at 0% in silence
                bar.set_postfix_str("compiling...")
            t0 = time.perf_counter()
            carry, out = chunk_fn(carry, jax.tree.map(lambda a: a[sl], padded), valid[sl])
            outputs.append(jax.tree.map(np.asarray, out))  # blocks until the chunk is done
            if start == 0:
                first_chunk_seconds = time.perf_counter() - t0
                bar.set_postfix_str("", refresh=False)
            bar.update(int(valid[sl].sum()))
            done = min(start + chunk_size, num_items)
            if on_chunk is not None and on_chunk(index, carry, lambda done=done: stack(done)) and done < num_items:
                num_done = done
                break
    return ChunkedRun(carry, stack(num_done), first_chunk_seconds, num_done)
