"""Tests of the course: tutorial.py (jupytext percent format) is the notebook's source, tutorial.ipynb is made from
it, and the notebook runs top to bottom."""
import pathlib

import jupytext
import nbclient
import nbformat

REPO = pathlib.Path(__file__).resolve().parent


def cell_sources(nb):
    return [(c.cell_type, c.source) for c in nb.cells]


def test_notebook_is_made_from_tutorial_py():
    """tutorial.ipynb holds exactly the cells of tutorial.py (regenerate: jupytext --update --to ipynb tutorial.py)."""
    source = jupytext.read(REPO / "tutorial.py")
    notebook = nbformat.read(REPO / "tutorial.ipynb", as_version=4)
    assert cell_sources(source) == cell_sources(notebook)


def test_the_comparison_catches_a_changed_cell():
    source = jupytext.read(REPO / "tutorial.py")
    changed = jupytext.read(REPO / "tutorial.py")
    changed.cells[3].source += "\nprint('drift')"
    assert cell_sources(source) != cell_sources(changed)


def test_tutorial_notebook_runs_in_quick_mode(monkeypatch):
    """tutorial.py executes top to bottom from a fresh kernel in quick mode (cwd = the repository) with no error,
    and every checkpoint it prints agrees with its expected value. About a minute on 2 cores."""
    nb = jupytext.read(REPO / "tutorial.py")
    monkeypatch.setenv("DIFFSTACK_QUICK", "1")  # the notebook's parameters cell reads it; the kernel inherits it
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(REPO)}})
    client.execute()  # raises CellExecutionError (naming the cell) on the first error
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "QUICK = True" in text
    checks = [line for line in text.splitlines() if line.startswith("CHECKPOINT")]
    assert len(checks) >= 8, checks
    assert not [line for line in checks if line.endswith("MISMATCH")], checks
