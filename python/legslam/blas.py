"""numpy's BLAS held to one thread where the engine's thread pools own the cores.

OpenBLAS's threads spin for a while after each call they share: beside a busy mapping pool, an
encoder and a tracker, that spinning takes a core's time from them (a tenth of a core through a
real-time 7-Scenes run), and one call can stall on threads that are not scheduled (the PCA's
384 x 384 eigendecomposition took 2.4 s on them, 45 ms on one thread).
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits

__all__ = ["one_blas_thread"]


def one_blas_thread():
    """A context in which every BLAS loaded (numpy's, and scipy's if it is) runs on one thread;
    the limits before are restored after. Process-wide, as BLAS's own setting is. The loaded
    libraries are looked up at each call (~1 ms): one loaded later would escape a list kept."""
    return threadpool_limits(limits=1, user_api="blas")
