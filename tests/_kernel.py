"""A notebook client for the tests."""

from nbclient import NotebookClient
from nbclient.util import ensure_async, run_hook


class NoHeartbeatClient(NotebookClient):
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
