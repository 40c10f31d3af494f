"""The notebooks run top to bottom (their own asserts check their results)."""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path):
    if path.stem == "03_real_data" and not DATA.exists():
        pytest.skip(f"no real data at {DATA}")
    nb = nbformat.read(path, as_version=4)
    os.environ.setdefault("SQPARTS_DATA", str(DATA))
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
