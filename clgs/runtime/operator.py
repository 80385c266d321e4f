"""The operator contract: what every OpenCL operator of :mod:`clgs.ops` is and does.

An operator is one class per kernel file (``SOURCE`` in ``cl/``) that owns what its calls need:

* **context and queue**, given explicitly (``ctx=``, ``queue=``; either implies the other) or,
  by default, the process's chosen device (:func:`clgs.runtime.use_device`);
* **program variants**: :meth:`Operator.variant` names each compiled variant by a key and builds
  it once with its ``-D`` defines (through the runtime's program cache);
* **launches** through :meth:`Operator.launch` only (the runtime's one launch helper), which
  also calls the **profiling hook** ``on_launch(kernel name, event)`` when one is set;
* **buffers** from its one :class:`~clgs.runtime.buffers.BufferPool` (``io``): pooled scratch,
  wrapped or copied inputs and outputs, long-lived constants and host blocks;
* **one lock**: every public call that touches the pool runs inside ``with self.call():``,
  which serialises the operator's calls and lets go of the call's host arrays at the end.

Process-wide instances (one per class and device, programs and buffers shared by every caller)
come from :func:`clgs.runtime.shared`.
"""
from __future__ import annotations

import threading
from contextlib import contextmanager

import pyopencl as cl

from .buffers import BufferPool
from .devices import get_context, get_queue
from .programs import get_program, launch


def context_and_queue(ctx=None, queue=None):
    """(context, in-order queue): both given, one implying the other, or the process's device."""
    if ctx is None and queue is None:
        return get_context(), get_queue()
    if ctx is None:
        ctx = queue.context
    elif queue is None:
        queue = get_queue() if ctx == get_context() else cl.CommandQueue(ctx)
    if queue.context != ctx:
        raise ValueError("the queue given belongs to another context than the one given")
    return ctx, queue


class Operator:
    """Base of the operators in :mod:`clgs.ops` (see the module doc for the contract);
    ``SOURCE`` names the kernel file in ``cl/``."""

    SOURCE = ""

    def __init__(self, ctx=None, queue=None):
        self.ctx, self.queue = context_and_queue(ctx, queue)
        self.device = self.queue.device
        self.cpu = bool(self.device.type & cl.device_type.CPU)
        self.io = BufferPool(self, self.cpu)
        self._lock = threading.RLock()
        self._depth = 0  # calls of this operator running in this thread (call() nests)
        self._variants: dict = {}
        self.on_launch = None  # profiling hook: called with (kernel name, event) after every launch

    def variant(self, key, defines, source: str | None = None):
        """The program variant ``key`` of ``source`` (default ``SOURCE``), built once with
        ``defines`` (a dict, or a callable making it, so that a known key costs one dictionary
        lookup)."""
        prog = self._variants.get((key, source))
        if prog is None:
            defs = defines() if callable(defines) else defines
            prog = self._variants[(key, source)] = get_program(source or self.SOURCE, defs, ctx=self.ctx)
        return prog

    def launch(self, prog, name: str, gsize, lsize, *args):
        """Enqueue kernel ``name`` of ``prog`` on this operator's queue (:func:`clgs.runtime.launch`)
        and report it to ``on_launch``. Returns the event."""
        event = launch(self.queue, prog.kernel(name), gsize, lsize, *args)
        if self.on_launch is not None:
            self.on_launch(name, event)
        return event

    @contextmanager
    def call(self):
        """One public call: holds the operator's lock (re-entrant: a call may use another of the
        same operator) and releases the host arrays the call's commands read when it ends (the
        call waits for its results before that)."""
        with self._lock:
            depth = self._depth
            self._depth = depth + 1
            try:
                yield self.io
            finally:
                self._depth = depth
                if depth == 0:
                    self.io.release()
