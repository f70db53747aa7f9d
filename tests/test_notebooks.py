"""Execute every notebook of ``notebooks/`` end to end, as CI does (issue 7).

Each notebook runs in a fresh kernel (the Python running the tests, through ipykernel) with a temporary
working directory, so nothing is written into the repository; the notebooks check their own results with
assertions in their last cell, and any exception fails the test. Skipped when nbclient or ipykernel is not
installed (they come with the ``dev`` extras). ``pytest --nbmake notebooks/`` runs the same notebooks.
"""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
CELL_TIMEOUT_S = 300  # per cell; every notebook takes well under a minute on a 2-core CI machine


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(notebook: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    nbformat = pytest.importorskip("nbformat", reason="nbformat is needed to read the notebooks")
    nbclient = pytest.importorskip("nbclient", reason="nbclient is needed to execute the notebooks")
    pytest.importorskip("ipykernel", reason="ipykernel is needed to run a notebook kernel")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # the kernel inherits it; the notebooks also set torch's

    nb = nbformat.read(notebook, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",  # jupyter_client starts it with the interpreter running the tests
        resources={"metadata": {"path": str(tmp_path)}},  # working directory of the kernel
    )
    client.execute()
    # the last code cell holds the notebook's assertions and ends by printing this
    last = [c for c in nb.cells if c.cell_type == "code"][-1]
    printed = "".join(o.get("text", "") for o in last.get("outputs", []) if o.get("output_type") == "stream")
    assert "all checks passed" in printed, printed


def test_notebooks_are_found_and_stored_without_outputs() -> None:
    assert len(NOTEBOOKS) >= 4, NOTEBOOKS
    nbformat = pytest.importorskip("nbformat", reason="nbformat is needed to read the notebooks")
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"{path.name}: clear the outputs"
