"""README.md's Python blocks run as written, on quick settings: a block that raises (a function
renamed, an argument gone, an attribute the result no longer has) fails here.

As written, the blocks map the 500-scan simulated office with 20 particles and localize with
1000: minutes on the project's 2-core machine. The test swaps in smaller sizes (and, for the
gradient, the proposal that compiles fastest) by replacing the exact text of a few arguments
(:data:`QUICK`), so that the code is the README's and only those arguments change; a replacement whose text the README no longer has fails the test, to be updated
with the README, rather than running the block at its full size."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"

QUICK = {
    # The office loop's first 40 scans (the README: 500): enough for the filter to take steps and
    # the refinement to match scans.
    "office_scenario(jax.random.key(0)).log": "office_scenario(jax.random.key(0), num_scans=40).log",
    # The learning block's log: 30 scans (the README: 100) for one gradient through the filter.
    "office_scenario(jax.random.key(0), num_scans=100).log": "office_scenario(jax.random.key(0), num_scans=30).log",
    # Fewer particles: the program is the same, only its size.
    "SlamConfig(num_particles=20, proposal=\"smp\")": "SlamConfig(num_particles=4, proposal=\"smp\")",
    # The learning block's filter with the OP, not the SMP: the SMP's gradient compiles for 60 s on
    # 2 cores (the OP's 15 s, measured), and the calls the block makes are the same
    # (tests/test_gradients.py differentiates the SMP).
    "{\"proposal\": \"smp\", \"num_particles\": 20}": "{\"proposal\": \"op\", \"num_particles\": 4}",
    "filter_settings(scenario, num_particles=1000)": "filter_settings(scenario, num_particles=100)",
}
"""README text -> the quick text the test runs instead (each must occur in some block)."""


def python_blocks(text: str) -> list[str]:
    """The ```python fenced blocks of a Markdown text, in order."""
    return re.findall(r"^```python[ \t]*\n(.*?)^```[ \t]*$", text, flags=re.M | re.S)


def quick(block: str) -> str:
    """``block`` with every :data:`QUICK` replacement it holds made."""
    for written, instead in QUICK.items():
        block = block.replace(written, instead)
    return block


BLOCKS = python_blocks(README.read_text())


def test_the_readme_has_its_blocks_and_every_quick_replacement_applies():
    assert len(BLOCKS) >= 3, f"README.md has {len(BLOCKS)} python blocks"
    text = "\n".join(BLOCKS)
    missing = [written for written in QUICK if written not in text]
    assert not missing, f"README.md no longer has {missing}: update QUICK in tests/test_readme.py with the README"


@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=lambda i: f"block{i + 1}")
def test_readme_block_runs(index):
    code = compile(quick(BLOCKS[index]), f"README.md python block {index + 1}", "exec")
    exec(code, {"__name__": f"readme_block_{index + 1}"})
