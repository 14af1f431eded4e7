from pathlib import Path

import nbformat
import pytest
from _kernel import NoHeartbeatClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
pytestmark = pytest.mark.slow  # 15-80 s each (a fresh kernel compiles everything); CI runs them


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path):
    """Every notebook runs top to bottom (its own asserts check the numbers)."""
    nb = nbformat.read(path, as_version=4)
    NoHeartbeatClient(nb, timeout=900, kernel_name="python3",
                       resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
