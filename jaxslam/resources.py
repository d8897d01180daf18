"""What a SLAM run needs of the machine, reckoned before any work: memory and disk.

The command line refuses a run that would not fit (``jaxslam map``), naming what to lower;
the same arithmetic sizes the first map pools (:func:`jaxslam.rbpf.pool_size`).
"""

from __future__ import annotations

import math

import numpy as np

from jaxslam.config import SlamConfig
from jaxslam.proposals import PROPOSALS
from jaxslam.rbpf import pool_size


def state_bytes(config: SlamConfig, first_scan_tiles: int | None = None) -> int:
    """Bytes of a run's particle set at the start (checkpointed with it): the directories
    (N x DY x DX int32), the block pool (B x S x S int32) and the tile pool (capacity x T x T
    cells of 3 bytes), as :func:`jaxslam.rbpf.pool_size` sizes them for a first scan of
    ``first_scan_tiles`` tiles (None: Intel's allowance, ``rbpf.TILES_PER_PARTICLE`` a particle)."""
    dy, dx = config.grid.num_blocks
    pools = pool_size(config, first_scan_tiles)
    return (4 * (config.num_particles * dy * dx + pools.block_capacity * config.grid.block_size**2)
            + 3 * pools.capacity * config.tile_size**2)


def map_cells(odometry, config: SlamConfig) -> int:
    """Cells of the map the outputs hold: about the odometry's (T, 3) extent plus the beams'
    reach (the outputs are cropped to the cells written)."""
    span = np.ptp(np.asarray(odometry)[:, :2], axis=0) + 2 * config.max_insert_range
    return int(math.ceil(span[0] / config.resolution) * math.ceil(span[1] / config.resolution))


def estimate_run_bytes(config: SlamConfig, num_beams: int, first_scan_tiles: int | None = None) -> tuple[int, str]:
    """A rough estimate of the memory (bytes) a ``run`` with ``config`` needs at its start, and how
    it was reckoned (for a refusal message).

    The tile pool (capacity x T x T x 3 bytes, twice: a chunk's input is kept to repeat it when
    the pool overflows) and the block pool (B x S x S int32, twice) as :func:`pool_size` sizes them
    for a first scan of ``first_scan_tiles`` tiles (None: Intel's allowance; the run sizes them
    from its log's, :func:`jaxslam.rbpf.first_scan_tiles`),
    the directories (N x DY x DX int32, twice), and scan insertion, which traces every beam with one
    sample per cell up to ``max_insert_range``: N x B x S samples of about 40 bytes. The proposal
    adds what its row's ``memory_fn`` says (the look-ahead: its N x L x B float32 beam terms, B the
    beams used in likelihoods, twice); about 1 GB is added for XLA (compiled code, buffers) and the host.
    The pools grow with the area mapped (they are reported in ``summary.json``).
    """
    n = config.num_particles
    dy, dx = config.grid.num_blocks
    t, s = config.tile_size, config.grid.block_size
    pool_sizes = pool_size(config, first_scan_tiles)
    state = state_bytes(config, first_scan_tiles) * 2
    samples = int(math.ceil(config.max_insert_range / config.resolution)) + 1
    insertion = n * num_beams * samples * 40
    how = (f"({n} particles x {dy} x {dx} blocks + {pool_sizes.block_capacity} blocks x {s} x {s} tiles) x 4 bytes "
           f"x 2 + {pool_sizes.capacity} tiles x {t} x {t} cells x 3 bytes x 2 + "
           f"{n} x {num_beams} beams x {samples} samples x 40 bytes")
    total = state + insertion + 2**30
    proposal_bytes, proposal_how = PROPOSALS[config.proposal].memory_fn(config, num_beams)
    if proposal_bytes:
        total += proposal_bytes
        how += f" + {proposal_how}"
    return total, how + " + 1 GB for XLA"


def available_memory_bytes() -> int | None:
    """The machine's available memory (``MemAvailable`` of /proc/meminfo, bytes); None if unreadable."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None
