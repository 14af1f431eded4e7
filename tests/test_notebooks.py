from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient
from nbclient.util import ensure_async, run_hook

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
pytestmark = pytest.mark.slow  # 15-80 s each (a fresh kernel compiles everything); CI runs them


class _NoHeartbeatClient(NotebookClient):
    """nbclient without the kernel's heartbeat channel. jupyter_client 8.10's heartbeat thread
    can hang ``stop_channels`` forever: once a ping goes unanswered (a loaded CI machine) it
    opens a fresh REQ socket and awaits a send that no peer will take after the kernel has shut
    down, and ``stop`` joins that thread (seen with gdb in a CI run that stalled in its slow
    suite). The kernel manager that started the kernel answers ``is_alive`` from the process
    itself, so nothing here needs the heartbeat."""

    async def async_start_new_kernel_client(self):
        self.kc = self.km.client()
        try:
            await ensure_async(self.kc.start_channels(hb=False))
            await ensure_async(self.kc.wait_for_ready(timeout=self.startup_timeout))
        except Exception:
            await self._async_cleanup_kernel()
            raise
        self.kc.allow_stdin = False
        await run_hook(self.on_notebook_start, notebook=self.nb)
        return self.kc


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path):
    """Every notebook runs top to bottom (its own asserts check the numbers)."""
    nb = nbformat.read(path, as_version=4)
    _NoHeartbeatClient(nb, timeout=900, kernel_name="python3",
                       resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
