"""Compile every Numba kernel once, or load it from the cache: ``python -m lc_petsc.elements.warm``.

``scripts/setup.sh`` runs it after the install, so the first simulation and the test suite
load the kernels from the cache instead of compiling them there (3.5 minutes on one core of
the machine of 2026-12-07).  The element kernels compile in this process while the contact,
cluster and curvature kernels compile in a child process: two cores halve the wait.
Numba writes each cache file aside and renames it, so the two processes may write the
entries of the functions they share.
"""

from __future__ import annotations

import subprocess
import sys
import time

#: the child's share: the contact kernels (the larger half), the cluster and curvature ones
_CHILD = ("from lc_petsc.elements import compiled_ccd, compiled_contact, compiled_cluster\n"
          "from lc_petsc import curvature\n"
          "for module in (compiled_ccd, compiled_contact, compiled_cluster, curvature):\n"
          "    module.warm_up()\n")


def warm_all() -> float:
    """Compile or load every kernel, two processes at once; the seconds it took.  Raises
    RuntimeError naming the child's exit status if its half failed."""
    t0 = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-c", _CHILD])
    try:
        from lc_petsc.elements import compiled, compiled_band, compiled_mult
        for module in (compiled, compiled_band, compiled_mult):
            module.warm_up()
    finally:
        status = child.wait()
    if status != 0:
        raise RuntimeError(f"compiling the contact kernels failed in the child process (exit {status}); "
                           "run `python -m lc_petsc.elements.warm` again to see its traceback")
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"setup: kernels compiled or loaded from the cache in {warm_all():.1f} s", flush=True)
