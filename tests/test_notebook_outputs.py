"""Every notebook in notebooks/ is committed executed, with its outputs: the README sends readers
to them, and a notebook without outputs shows nothing on GitHub.

The rule, on the committed JSON (no kernel, no JAX: this runs in well under a second): at least
one code cell has outputs; every code cell with source has an execution count, the counts rise
from top to bottom (one run, top to bottom); no output is an error. tests/test_notebooks.py
checks separately that each notebook still runs.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def unexecuted(notebook: dict) -> list[str]:
    """What keeps a notebook (its JSON, as a dict) from counting as committed with its outputs."""
    code = [cell for cell in notebook.get("cells", []) if cell.get("cell_type") == "code"]
    problems = []
    if not any(cell.get("outputs") for cell in code):
        problems.append("no code cell has outputs")
    counts = []
    for index, cell in enumerate(code):
        source = "".join(cell.get("source", []))
        if not source.strip():
            continue
        count = cell.get("execution_count")
        if count is None:
            problems.append(f"code cell {index} was not executed (execution_count is null)")
        else:
            counts.append(count)
        if any(output.get("output_type") == "error" for output in cell.get("outputs", [])):
            problems.append(f"code cell {index} holds an error")
    if counts != sorted(counts) or len(set(counts)) != len(counts):
        problems.append(f"execution counts {counts} are not one top-to-bottom run")
    for index, cell in enumerate(code):
        text = json.dumps(cell.get("outputs", []))
        for prefix in MACHINE_PATHS:
            if prefix in text:
                problems.append(f"code cell {index}'s output names a path of the machine it ran on ({prefix}...)")
    return problems


MACHINE_PATHS = ("/root/", "/home/", "/work/", "/tmp/", "/Users/", "C:\\\\Users")
"""Output text that would point outside the repository (a warning's file name, a data folder)."""


def test_there_are_notebooks():
    assert NOTEBOOKS


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_committed_with_outputs(path):
    problems = unexecuted(json.loads(path.read_text(encoding="utf-8")))
    assert not problems, (f"{path.name}: {problems}; execute it and commit it with its outputs "
                          f"(nbclient, or jupyter nbconvert --to notebook --execute --inplace)")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_the_check_fails_on_a_stripped_copy(path):
    """The same notebook with its outputs and counts stripped (as nbstripout leaves it), with one
    cell stripped, and with one cell's output an error: each fails the check."""
    notebook = json.loads(path.read_text(encoding="utf-8"))
    code = [cell for cell in notebook["cells"] if cell["cell_type"] == "code" and "".join(cell["source"]).strip()]

    stripped = json.loads(json.dumps(notebook))
    for cell in stripped["cells"]:
        if cell["cell_type"] == "code":
            cell["outputs"], cell["execution_count"] = [], None
    assert "no code cell has outputs" in unexecuted(stripped)

    one_cell = json.loads(json.dumps(notebook))
    last = [cell for cell in one_cell["cells"] if cell["cell_type"] == "code" and "".join(cell["source"]).strip()][-1]
    last["outputs"], last["execution_count"] = [], None
    assert any("not executed" in p for p in unexecuted(one_cell))

    errored = json.loads(json.dumps(notebook))
    first = [cell for cell in errored["cells"] if cell["cell_type"] == "code" and "".join(cell["source"]).strip()][0]
    first["outputs"] = [{"output_type": "error", "ename": "E", "evalue": "", "traceback": []}]
    assert any("error" in p for p in unexecuted(errored))

    pathful = json.loads(json.dumps(notebook))
    first = [cell for cell in pathful["cells"] if cell["cell_type"] == "code" and "".join(cell["source"]).strip()][0]
    first["outputs"] = first["outputs"] + [{"output_type": "stream", "name": "stderr",
                                            "text": ["/home/me/lib/tqdm/auto.py:21: TqdmWarning"]}]
    assert any("path of the machine" in p for p in unexecuted(pathful))

    if len(code) > 1:
        reordered = json.loads(json.dumps(notebook))
        cells = [cell for cell in reordered["cells"] if cell["cell_type"] == "code" and "".join(cell["source"]).strip()]
        cells[0]["execution_count"], cells[1]["execution_count"] = 2, 1
        assert any("top-to-bottom" in p for p in unexecuted(reordered))
