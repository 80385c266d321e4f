"""What every OpenCL operator holds: the context and queue it runs on, whether device memory is
host memory (a CPU device), a pool of reusable device buffers, a lock that serialises its calls
and its compiled program variants (one per set of ``-D`` defines, kept so a call does not even
pay the runtime cache's lookup)."""
from __future__ import annotations

import threading

import pyopencl as cl

from clgs import runtime
from clgs.runtime.buffers import BufferPool


class Operator:
    """Base of the operators in :mod:`clgs.ops`; ``SOURCE`` names the kernel file in ``cl/``."""

    SOURCE = ""

    def __init__(self, ctx=None, queue=None):
        self.ctx = ctx or runtime.get_context()
        self.queue = queue or runtime.get_queue()
        self.cpu = bool(self.ctx.devices[0].type & cl.device_type.CPU)
        self.io = BufferPool(self, self.cpu)
        self._lock = threading.Lock()
        self._variants: dict = {}

    def build(self, defines: dict, source: str | None = None):
        """The program of ``source`` (default ``SOURCE``) with these defines, from the runtime's cache."""
        return runtime.get_program(source or self.SOURCE, defines, ctx=self.ctx)

    def variant(self, key, defines, source: str | None = None):
        """The program variant ``key``, built once with ``defines`` (a dict, or a callable making
        it, so that a known key costs one dictionary lookup)."""
        prog = self._variants.get(key)
        if prog is None:
            prog = self._variants[key] = self.build(defines() if callable(defines) else defines, source)
        return prog
