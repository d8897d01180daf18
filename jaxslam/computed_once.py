"""``computed_once``: make XLA compute an array into memory once instead of fusing it into every reader.

XLA fuses a cheap-looking elementwise producer into every consumer. When the consumers are
gathers and scatters (the beam samples of a map insertion, read by several scatters; the beam
endpoints of a likelihood, read by a page-table gather and then a pool gather), the producer is
recomputed inside each of them, in scalar loops, once per read. The workaround: the outputs of a
loop whose trip count XLA cannot know are always materialised, by vectorised code, once. So
:func:`computed_once` runs the producer in a ``while_loop`` whose trip count depends on the data
(and is in fact always 1 or 2, with the same result). ``jax.lax.optimization_barrier`` does not
do this: XLA's CPU pipeline drops it before fusion. The measurements are in
``docs/design.md``, "Maps are paged".

Also here, the other loop workaround the maps need: :func:`loop_bound`, a ``while_loop``'s trip
count that stays one number under ``vmap`` (a batched predicate makes JAX select every carry,
the map pools included, at every round).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def computed_once(fn, first, *rest):
    """``fn(first, *rest)``, computed into memory once, before anything reads it.

    ``fn`` runs in a ``while_loop`` of 1 trip, or 2 if ``first``'s first element is above the
    float32 maximum (the same result either way): XLA cannot know the trip count, so it
    materialises the outputs instead of fusing ``fn`` into their readers (see the module
    docstring). Reverse-mode autodiff cannot go through a ``while_loop``, so the derivative is
    ``fn``'s own (a custom JVP): the forward values are the loop's, gradients flow as if ``fn``
    were called directly.
    """
    # closure_convert: the custom JVP must not close over traced values (fn often does).
    converted, consts = jax.closure_convert(fn, first, *rest)
    return _computed_once(converted, first, *rest, *consts)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _computed_once(fn, first, *rest):
    """``fn(first, *rest)`` inside a ``while_loop`` whose trip count depends on ``first``."""
    shapes = jax.eval_shape(fn, first, *rest)
    init = jax.tree.map(lambda shape: jnp.zeros(shape.shape, shape.dtype), shapes)
    probe = first.reshape(-1)[0].astype(jnp.float32)
    trips = 1 + (probe > jnp.finfo(jnp.float32).max).astype(jnp.int32)
    _, out = jax.lax.while_loop(lambda c: c[0] < trips, lambda c: (c[0] + 1, fn(first, *rest)),
                                (jnp.int32(0), init))
    return out


@_computed_once.defjvp
def _computed_once_jvp(fn, primals, tangents):
    """The loop's forward values with ``fn``'s own tangents."""
    _, tangents_out = jax.jvp(fn, primals, tangents)
    return _computed_once(fn, *primals), tangents_out


@custom_vmap
def loop_bound(count):
    """``count`` (an int scalar), as the bound of a ``while_loop`` whose rounds past a run's own
    count change nothing (they read and write nothing live). Under ``vmap`` it is the largest
    count of the batch, one number, not a batched one: JAX batches a ``while_loop`` whose
    predicate is batched by selecting between the old and the new value of every carry at every
    round, which for a loop that scatters into the map pools is a copy of the pools per round.
    The runs of the batch then take as many rounds as the longest needs, the others' extra rounds
    doing nothing, so each run's values are those of its own loop."""
    return count


@loop_bound.def_vmap
def _loop_bound_vmap(axis_size, in_batched, count):
    del axis_size
    return (jnp.max(count, axis=0) if in_batched[0] else count), False
