"""Every notebook in notebooks/ runs top to bottom on small settings (JAXSLAM_QUICK=1).

notebooks/real_log.ipynb maps a real log from ``JAXSLAM_DATA``, set here to the tests' data
folder (conftest.SHARED_DATA); where that folder lacks the log the notebook says it skips and
its cells do nothing, and where it has it the notebook must have mapped and evaluated it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import SHARED_DATA

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path, monkeypatch):
    monkeypatch.setenv("JAXSLAM_QUICK", "1")
    monkeypatch.setenv("JAXSLAM_DATA", str(SHARED_DATA))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    errors = [o for o in outputs if o.get("output_type") == "error"]
    assert not errors
    if path.stem == "real_log":
        printed = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
        if (SHARED_DATA / "intel.sort.bag").is_file() and (SHARED_DATA / "intel.relations").is_file():
            assert "relations inside the mapped span" in printed and "coalescence_step" in printed
        else:
            assert "skipping" in printed
