"""What holds between any two operations on paged maps, checked on the host:
:func:`check_invariants` (entries in range, reference counts equal to a recount, one place per
block and tile, free lists, peaks, and all or nothing across an insertion)."""

from __future__ import annotations

import numpy as np

from jaxslam.maps.pool import UNWRITTEN, PagedGridSpec, PagedMaps, blocks_in_use, tiles_in_use
from jaxslam.occupancy import LOGODDS_DTYPE


def check_invariants(spec: PagedGridSpec, maps: PagedMaps, before_insertion: PagedMaps | None = None) -> None:
    """Check on the host that ``maps`` are consistent; raise AssertionError naming the first
    broken invariant (ValueError if the arrays are not shaped as ``spec``'s maps are).

    These hold after :func:`~jaxslam.maps.empty`, :func:`~jaxslam.maps.insert_scans`,
    :func:`~jaxslam.maps.resample` and :func:`~jaxslam.maps.grow`:

    1. *directory entries*: every directory entry is :data:`UNWRITTEN` or a block slot (0 <= b < B).
    2. *block references*: ``block_refcount[b]`` is the number of directory entries equal to b
       (a block is *in use* when it is > 0; a free block slot is in no directory).
    3. *block entries*: every entry of a block in use is :data:`UNWRITTEN` or a tile slot
       (0 <= c < C). A free block's entries are stale: never read, overwritten whole when granted.
    4. *tile references*: ``refcount[c]`` is the number of entries of blocks in use equal to c
       (blocks, not particles: particles sharing a block share its tiles' references); a free
       tile slot is in no block in use. A free tile's cells are stale likewise.
    5. *one place per block*: a block in use sits at the same directory entry (row, col) in every
       directory that points at it (a copy is made for the place of the block it replaces).
    6. *tiles beyond the grid*: the entries of a block in use for tiles past the virtual grid's
       last row or column (where the block size does not divide the tile counts) are
       :data:`UNWRITTEN`.
    7. *one place per tile*: every block entry that points at a tile slot stands for the same
       (row, col) tile of the virtual grid.
    8. *free lists*: ``free_slots`` is the first M slots of refcount 0 in order, padded with C;
       ``free_blocks`` the first MB of block refcount 0, padded with B.
    9. *peak requests*: ``peak_request`` and ``peak_block_request`` are not negative.

    With ``before_insertion``, the maps the :func:`~jaxslam.maps.insert_scans` call that gave
    ``maps`` started from (not across a :func:`~jaxslam.maps.resample`, which keeps ``overflow`` as
    it was), also:

    10. *peaks never fall*: each peak request is at least its value before.
    11. *peaks cover the growth*: the tiles (blocks) in use grew by at most ``peak_request``
        (``peak_block_request``): every slot newly in use was requested.
    12. *all or nothing*: with ``overflow`` set, the directories, pools, reference counts and
        free lists are exactly those before, and a request did not fit: ``peak_request`` exceeds
        M or the free tile slots before, or ``peak_block_request`` MB or the free block slots.
    """
    _check_shapes(spec, maps)
    blocks_in_use = _check_references(maps)
    _check_places(spec, maps, blocks_in_use)
    _check_free_lists_and_peaks(maps)
    if before_insertion is not None:
        _check_insertion(spec, before_insertion, maps)


def _broken(invariant: str, detail: str):
    """Fail with the invariant's name (as :func:`check_invariants` lists it) and what broke it."""
    raise AssertionError(f"paged maps: invariant '{invariant}' is broken: {detail}")


def _check_shapes(spec: PagedGridSpec, maps: PagedMaps) -> None:
    """ValueError unless every array of ``maps`` has the shape and type of ``spec``'s maps."""
    n, t, s = maps.directory.shape[0], spec.tile_size, spec.block_size
    capacity, block_capacity = maps.refcount.shape[0], maps.block_refcount.shape[0]
    expected = {"directory": ((n,) + spec.num_blocks, np.int32), "blocks": ((block_capacity, s, s), np.int32),
                "block_refcount": ((block_capacity,), np.int32), "logodds": ((capacity, t, t), LOGODDS_DTYPE),
                "hit_dist2": ((capacity, t, t), np.uint8), "refcount": ((capacity,), np.int32),
                "free_slots": ((maps.free_slots.shape[0],), np.int32),
                "free_blocks": ((maps.free_blocks.shape[0],), np.int32), "overflow": ((), np.bool_),
                "peak_request": ((), np.int32), "peak_block_request": ((), np.int32)}
    for name, (shape, dtype) in expected.items():
        value = getattr(maps, name)
        if tuple(value.shape) != shape or np.dtype(value.dtype) != np.dtype(dtype):
            raise ValueError(f"paged maps: {name} is {np.dtype(value.dtype)}{tuple(value.shape)}, expected "
                             f"{np.dtype(dtype)}{shape} for {spec}")
    if maps.max_new_tiles > capacity or maps.pool_size.max_new_blocks > block_capacity:
        raise ValueError(f"paged maps: free lists longer than their pools ({maps.pool_size})")


def _check_references(maps: PagedMaps) -> np.ndarray:
    """Invariants 1 to 4: entries in range, reference counts equal to a recount. Returns the
    block slots in use."""
    directory, blocks = np.asarray(maps.directory), np.asarray(maps.blocks)
    refcount, block_refcount = np.asarray(maps.refcount), np.asarray(maps.block_refcount)
    capacity, block_capacity = refcount.size, block_refcount.size
    bad = (directory < UNWRITTEN) | (directory >= block_capacity)
    if bad.any():
        _broken("directory entries", f"{np.count_nonzero(bad)} entries neither UNWRITTEN nor in [0, "
                f"{block_capacity}), e.g. {directory[bad][:4]}")
    counted = np.bincount(directory[directory >= 0], minlength=block_capacity)
    if not np.array_equal(block_refcount, counted):
        wrong = np.flatnonzero(block_refcount != counted)[:4]
        _broken("block references", f"block slots {wrong} have refcount {block_refcount[wrong]}, but "
                f"{counted[wrong]} directory entries point at them")
    in_use = np.flatnonzero(counted > 0)
    entries = blocks[in_use]
    bad = (entries < UNWRITTEN) | (entries >= capacity)
    if bad.any():
        _broken("block entries", f"{np.count_nonzero(bad)} entries of blocks in use neither UNWRITTEN nor in "
                f"[0, {capacity}), e.g. {entries[bad][:4]}")
    counted = np.bincount(entries[entries >= 0], minlength=capacity)
    if not np.array_equal(refcount, counted):
        wrong = np.flatnonzero(refcount != counted)[:4]
        _broken("tile references", f"tile slots {wrong} have refcount {refcount[wrong]}, but {counted[wrong]} "
                "entries of blocks in use point at them")
    return in_use


def _one_place_each(slots: np.ndarray, places: np.ndarray, num_slots: int) -> np.ndarray:
    """Per slot: every occurrence of it in ``slots`` (>= 0) comes with the same value of ``places``."""
    used = slots >= 0
    low, high = np.full(num_slots, np.iinfo(np.int64).max), np.full(num_slots, -1)
    np.minimum.at(low, slots[used], places[used])
    np.maximum.at(high, slots[used], places[used])
    return (high < 0) | (low == high)


def _check_places(spec: PagedGridSpec, maps: PagedMaps, in_use: np.ndarray) -> None:
    """Invariants 5 to 7: each block and tile slot in use stands for one place of the grid."""
    directory, entries = np.asarray(maps.directory), np.asarray(maps.blocks)[in_use]
    s, (ty, tx), (dy, dx) = spec.block_size, spec.num_tiles, spec.num_blocks
    place = np.broadcast_to(np.arange(dy * dx).reshape(dy, dx), directory.shape)
    one_place = _one_place_each(directory, place, maps.block_refcount.shape[0])
    if not one_place.all():
        _broken("one place per block", f"block slots {np.flatnonzero(~one_place)[:4]} sit at different "
                "directory entries in different directories")
    block_place = np.zeros(maps.block_refcount.shape[0], np.int64)
    block_place[directory[directory >= 0]] = place[directory >= 0]
    tile_rows = (block_place[in_use] // dx)[:, None, None] * s + np.arange(s)[None, :, None]  # (U, S, 1)
    tile_cols = (block_place[in_use] % dx)[:, None, None] * s + np.arange(s)[None, None, :]  # (U, 1, S)
    bad = ((tile_rows >= ty) | (tile_cols >= tx)) & (entries != UNWRITTEN)
    if bad.any():
        _broken("tiles beyond the grid", f"blocks in use point at tile slots {entries[bad][:4]} for tiles past the "
                "virtual grid's edge")
    one_place = _one_place_each(entries, np.broadcast_to(tile_rows * (dx * s) + tile_cols, entries.shape),
                                maps.capacity)
    if not one_place.all():
        _broken("one place per tile", f"tile slots {np.flatnonzero(~one_place)[:4]} stand for different tiles of "
                "the virtual grid in different block entries")


def _check_free_lists_and_peaks(maps: PagedMaps) -> None:
    """Invariants 8 and 9."""
    for name, free, refcount in (("free_slots", maps.free_slots, maps.refcount),
                                 ("free_blocks", maps.free_blocks, maps.block_refcount)):
        refcount = np.asarray(refcount)
        expected = np.flatnonzero(refcount == 0)[:free.shape[0]]
        expected = np.concatenate([expected, np.full(free.shape[0] - expected.size, refcount.size)])
        if not np.array_equal(np.asarray(free), expected):
            _broken("free lists", f"{name} is {np.asarray(free)}, but the first slots of refcount 0 are {expected}")
    peaks = int(maps.peak_request), int(maps.peak_block_request)
    if min(peaks) < 0:
        _broken("peak requests", f"negative peak requests {peaks}")


def _check_insertion(spec: PagedGridSpec, before: PagedMaps, after: PagedMaps) -> None:
    """Invariants 10 to 12 of :func:`check_invariants`, across one insertion."""
    _check_shapes(spec, before)
    if before.pool_size != after.pool_size or before.directory.shape != after.directory.shape:
        raise ValueError(f"paged maps: an insertion keeps the pools' sizes and the particles, but "
                         f"{before.pool_size} became {after.pool_size}")
    peaks = int(after.peak_request), int(after.peak_block_request)
    peaks_before = int(before.peak_request), int(before.peak_block_request)
    if peaks[0] < peaks_before[0] or peaks[1] < peaks_before[1]:
        _broken("peaks never fall", f"peak requests (tiles, blocks) {peaks_before} fell to {peaks}")
    growth = (int(tiles_in_use(after)) - int(tiles_in_use(before)),
              int(blocks_in_use(after)) - int(blocks_in_use(before)))
    if growth[0] > peaks[0] or growth[1] > peaks[1]:
        _broken("peaks cover the growth", f"(tiles, blocks) in use grew by {growth}, more than the peak requests "
                f"{peaks}")
    if bool(after.overflow):
        for name in ("directory", "blocks", "block_refcount", "logodds", "hit_dist2", "refcount", "free_slots",
                     "free_blocks"):
            if not np.array_equal(np.asarray(getattr(after, name)), np.asarray(getattr(before, name))):
                _broken("all or nothing", f"overflow is set, but the insertion changed {name}")
        _, max_new_tiles, _, max_new_blocks = after.pool_size
        free_tiles = int(np.count_nonzero(np.asarray(before.refcount) == 0))
        free_blocks = int(np.count_nonzero(np.asarray(before.block_refcount) == 0))
        if peaks[0] <= min(max_new_tiles, free_tiles) and peaks[1] <= min(max_new_blocks, free_blocks):
            _broken("all or nothing", f"overflow is set, but peak requests {peaks} fit (at most "
                    f"{min(max_new_tiles, free_tiles)} tiles and {min(max_new_blocks, free_blocks)} blocks)")
