"""Entry point of a service process started by the runner: ``python -P -m services.runner.child NAME PARENT_PID``.

On Linux it first asks the kernel to send it SIGTERM when the runner dies (``PR_SET_PDEATHSIG``), so a runner
that is killed outright (SIGKILL, the OOM killer) leaves no service behind: each stops as on ``docker stop``.
Then it runs ``services.NAME`` exactly as ``kmvipe service NAME`` does. Nothing here needs the working directory.
"""
from __future__ import annotations

import ctypes
import importlib
import os
import signal
import sys


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int) -> None:
    """Have SIGTERM delivered to this process when its parent exits (Linux; elsewhere a no-op), and exit at once
    if the parent is already gone (it may have died between the fork and this call)."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
                print(f"prctl(PR_SET_PDEATHSIG) failed: errno {ctypes.get_errno()}", file=sys.stderr)
        except (OSError, AttributeError):  # no usable libc: the runner's own stop still applies
            pass
    if os.getppid() != parent_pid:
        sys.exit(f"the runner (pid {parent_pid}) exited before this service started")


def main(argv: list[str] | None = None) -> int:
    name, parent_pid = (argv if argv is not None else sys.argv[1:])[:2]
    die_with_parent(int(parent_pid))
    sys.argv = [f"kmvipe service {name}"]
    return importlib.import_module(f"services.{name}.__main__").main()


if __name__ == "__main__":
    sys.exit(main())
