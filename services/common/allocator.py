"""Which malloc a service process runs on: glibc's, or TCMalloc (gperftools) preloaded into it.

ba's dense BAs allocate and free gigabytes of mid-size buffers (a 48-edge slice's (edges, pixels) fields,
0.6–7 MB each) between long-lived arrays. glibc's heap cuts up around them: over 5,000 frames of the memory check
ba's level rose 729 → 816 MB (+12 %) while nothing it holds grew, and the trims, own pages and arena limits of earlier
sessions only slowed that (docs/BENCHMARKS.md). TCMalloc keeps freed memory in size classes, so a later BA reuses
what an earlier one freed; the same BA also runs ~20 % faster on it. The PyTorch performance guide recommends it
for CPU work for the same reasons.

A library chosen here must be in the process before the service's work allocates, so every service's
``service_main`` calls :func:`ensure` first: when the chosen allocator is not the one in use, the process executes
itself again with ``LD_PRELOAD`` set (same pid, same command line, before the bus exists). ``kmvipe run``, ``kmvipe
service``, ``python -m services.NAME`` and the containers all go through it, so one setting covers every
deployment.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys
from typing import TYPE_CHECKING

from services.common.errors import KmVipeError

if TYPE_CHECKING:
    from services.common.config import MallocSettings

log = logging.getLogger(__name__)

# where TCMalloc measured better over a long stream (docs/BENCHMARKS.md, forty-seventh session): ba. The mapstore
# held 35 MB more on it and grew as much; the others keep glibc, tuned for their frame-sized buffers (bench/bus.py)
PREFERRED: dict[str, str] = {"ba": "tcmalloc"}

# gperftools' allocator without its heap profiler (Debian/Ubuntu: libtcmalloc-minimal4; Alpine, Fedora: gperftools)
_LIBRARIES = {"tcmalloc": ("tcmalloc_minimal", "tcmalloc")}
# set in the environment of the process executed again, so that a preload the loader ignored cannot loop, and
# what LD_PRELOAD held before, given back to the process's own children (ba's tracking process stays on glibc:
# 57 MB there against 73 MB on TCMalloc, docs/BENCHMARKS.md)
_REEXEC_GUARD = "KMVIPE_MALLOC_PRELOADED"
_PRELOAD_BEFORE = "KMVIPE_MALLOC_LD_PRELOAD_BEFORE"


def in_use() -> str:
    """The allocator serving this process's ``malloc``: "tcmalloc" when gperftools' is loaded, else "glibc"."""
    try:
        process = ctypes.CDLL(None)
    except OSError:
        return "glibc"
    return "tcmalloc" if hasattr(process, "MallocExtension_ReleaseFreeMemory") else "glibc"


def library(allocator: str) -> str | None:
    """The shared library of ``allocator`` as the dynamic loader finds it (its soname), or None if not installed
    or not on Linux (``LD_PRELOAD`` is the Linux loader's)."""
    if not sys.platform.startswith("linux"):
        return None
    for name in _LIBRARIES.get(allocator, ()):
        found = ctypes.util.find_library(name)
        if found:
            return found
    return None


def chosen(service: str, setting: str) -> str | None:
    """The allocator ``service`` should run on under ``setting``; None where ``auto`` would pick one that is not
    installed (glibc then). Raises :class:`KmVipeError`, with how to install it, for an explicit one that is not."""
    wanted = PREFERRED.get(service, "glibc") if setting == "auto" else setting
    if wanted == "glibc" or library(wanted) is not None:
        return wanted
    if setting == "auto":
        return None
    raise KmVipeError(f"KMVIPE_MALLOC_ALLOCATOR={wanted}, but its library is not installed: install it "
                      "(Debian/Ubuntu: apt-get install libtcmalloc-minimal4) or set KMVIPE_MALLOC_ALLOCATOR=glibc")


def preload_environment(allocator: str, environ: dict[str, str]) -> dict[str, str]:
    """``environ`` with ``allocator``'s library first in ``LD_PRELOAD`` (and the guard against a second exec)."""
    found = library(allocator)
    if found is None:
        raise KmVipeError(f"no library for allocator {allocator!r}")
    before = environ.get("LD_PRELOAD", "")
    preload = " ".join(p for p in (found, before) if p)
    return {**environ, "LD_PRELOAD": preload, _REEXEC_GUARD: allocator, _PRELOAD_BEFORE: before}


def _restore_children_environment() -> None:
    """After the exec: LD_PRELOAD as it was before, so the processes this one starts run on their own choice."""
    before = os.environ.pop(_PRELOAD_BEFORE, None)
    os.environ.pop(_REEXEC_GUARD, None)
    if before is None:
        return
    if before:
        os.environ["LD_PRELOAD"] = before
    else:
        os.environ.pop("LD_PRELOAD", None)


def ensure(service: str, settings: "MallocSettings | None" = None) -> None:
    """Make this process run on ``service``'s allocator: returns when it already does (or should stay on glibc);
    else executes the process again with the library preloaded and does not return. Call it first thing in a
    process's entry point, never in a process that runs other work (a test runner): the exec replaces it.

    Raises :class:`KmVipeError` when an explicitly chosen allocator is not installed."""
    if settings is None:
        # here, not at the top: lifecycle imports this module into ba's tracking process, which has no use for
        # pydantic (+19 MB there)
        from pydantic import ValidationError

        from services.common.config import MallocSettings
        try:
            settings = MallocSettings()
        except ValidationError as exc:
            raise KmVipeError(f"invalid settings (check KMVIPE_MALLOC_* and the KMVIPE_CONFIG file):\n{exc}") from exc
    wanted = chosen(service, settings.allocator)
    executed_again = os.environ.get(_REEXEC_GUARD)
    if executed_again is not None:
        _restore_children_environment()
    if wanted is None or wanted == in_use():
        return
    if wanted == "glibc":  # a preload asked for in the environment by someone else: theirs to choose
        return
    if executed_again == wanted:  # preloaded, yet not in use: the loader refused the library
        log.warning(f"{service}: {library(wanted)} was preloaded but is not in use; running on glibc "
                    f"(KMVIPE_MALLOC_ALLOCATOR=glibc says so without trying)")
        return
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], preload_environment(wanted, dict(os.environ)))
