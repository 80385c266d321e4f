"""How the OpenCL operators hand NumPy arrays to their kernels and get results back.

On a CPU device an array's own memory is wrapped (``USE_HOST_PTR``): no copies in, and results
become visible in the array by mapping its buffer. On other devices arrays are copied to device
buffers and back. Scratch buffers (lists, partial sums, records) are pooled by name and reused
call after call, grown by a quarter when too small, so a training loop allocates nothing.

One :class:`BufferPool` per operator instance (:class:`clgs.runtime.operator.Operator`), used
inside the operator's lock (``with op.call():``), never from two threads at once.
"""
from __future__ import annotations

import numpy as np

from clgs.runtime.programs import round_up


class BufferPool:
    """An operator's device buffers: pooled scratch, wrapped or copied inputs and outputs, and
    the host arrays that queued commands still read (kept referenced until :meth:`release`)."""

    def __init__(self, owner, host_memory: bool):
        self._owner = owner  # the operator: its context and queue, read at each use (a benchmark may swap the queue)
        self.host_memory = bool(host_memory)  # wrap host arrays (CPU devices) or copy them
        self._pool: dict = {}
        self._host: dict = {}
        self.keep: list = []

    @property
    def ctx(self):
        return self._owner.ctx

    @property
    def queue(self):
        return self._owner.queue

    # ------------------------------------------------------------------------ scratch
    def scratch(self, name: str, nbytes: int):
        """A device buffer of at least ``nbytes`` (contents left from earlier calls)."""
        import pyopencl as cl

        nbytes = max(int(nbytes), 64)
        buf = self._pool.get(name)
        if buf is None or buf.size < nbytes:
            buf = self._pool[name] = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE,
                                               size=round_up(nbytes + nbytes // 4, 4096))
        return buf

    def pooled(self, name: str):
        """The scratch buffer ``name`` as it is (a result an earlier call left there)."""
        return self._pool[name]

    def new(self, nbytes: int):
        """A device buffer of ``nbytes`` that the caller keeps (tables cached across calls); not pooled."""
        import pyopencl as cl

        return cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, size=max(int(nbytes), 64))

    def constant(self, arr: np.ndarray):
        """A read-only device copy of ``arr`` that the caller keeps as long as it likes (tables
        cached across calls); not pooled, ``arr`` may go right away."""
        import pyopencl as cl

        return cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=arr)

    def host_block(self, name: str, nbytes: int, align: int = 4096):
        """(host byte array, buffer): a pooled ``align``-aligned host array of at least ``nbytes``
        (a power of two, 4 KiB at least) with a buffer kernels write into: its own memory on a CPU
        device, a device buffer that :meth:`fetch` copies back otherwise. Sub-buffers of one block
        let one map or copy bring several outputs back."""
        import pyopencl as cl

        entry = self._host.get(name)
        if entry is None or entry[0].size < nbytes:
            size = 1 << max(int(max(nbytes, 1) - 1).bit_length(), 12)
            raw = np.zeros(size + align, np.uint8)
            off = -raw.ctypes.data % align
            arr = raw[off:off + size]
            if self.host_memory:
                buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)
            else:
                buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, size=size)
            entry = self._host[name] = (arr, buf)
        return entry

    def copy(self, dst, src, **kwargs):
        """Enqueue a copy between buffers (or a buffer and a host array) on the operator's queue."""
        import pyopencl as cl

        return cl.enqueue_copy(self.queue, dst, src, **kwargs)

    def fill(self, buf, pattern, nbytes: int | None = None):
        """Enqueue filling ``nbytes`` (default all) of ``buf`` with the NumPy scalar/array ``pattern``."""
        import pyopencl as cl

        return cl.enqueue_fill_buffer(self.queue, buf, pattern, 0, buf.size if nbytes is None else nbytes)

    # ------------------------------------------------------------------------ host arrays
    def wrap(self, arr: np.ndarray):
        """A read-only buffer of ``arr``'s contents; the caller keeps ``arr`` alive until the
        commands that read it are done (its own memory on a CPU device, a copy otherwise)."""
        import pyopencl as cl

        mf = cl.mem_flags
        return cl.Buffer(self.ctx, mf.READ_ONLY | (mf.USE_HOST_PTR if self.host_memory else mf.COPY_HOST_PTR),
                         hostbuf=arr)

    def input(self, arr: np.ndarray, name: str | None = None):
        """A read-only buffer of ``arr``, which stays referenced until :meth:`release`. On a
        device that copies, ``name`` copies into a pooled buffer instead of a new one."""
        import pyopencl as cl

        if arr.size == 0:
            return self.scratch(f"{name}:empty", 64)
        if not (arr.flags.c_contiguous and arr.flags.writeable):
            arr = np.array(arr, order="C")  # drivers wrap writable C-ordered memory only
        self.keep.append(arr)
        if self.host_memory or name is None:
            return self.wrap(arr)
        buf = self.scratch(name, arr.nbytes)
        cl.enqueue_copy(self.queue, buf, arr, is_blocking=False)
        return buf

    def output(self, arr: np.ndarray, name: str | None = None, initial: bool = False):
        """A buffer the kernels write ``arr``'s results into (see :meth:`fetch`): its own memory
        on a CPU device; otherwise the pooled buffer ``name`` or a new one, holding ``arr``'s
        contents first when ``initial`` (kernels that write only some entries)."""
        import pyopencl as cl

        mf = cl.mem_flags
        if self.host_memory and arr.size:
            return cl.Buffer(self.ctx, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=arr)
        if initial and arr.size:
            if name is None:
                return cl.Buffer(self.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=arr)
            buf = self.scratch(name, arr.nbytes)
            self.keep.append(arr)
            cl.enqueue_copy(self.queue, buf, arr, is_blocking=False)
            return buf
        if name is None:
            return cl.Buffer(self.ctx, mf.READ_WRITE, size=max(arr.nbytes, 64))
        return self.scratch(name, arr.nbytes)

    def zeros(self, name: str, n: int):
        """(buffer, array): ``n`` int32 zeros for the kernels to count into, and the host array
        :meth:`fetch` reads them back to."""
        arr = np.zeros(n, np.int32)
        return self.output(arr, name, initial=True), arr

    def fetch(self, pairs) -> None:
        """Make every array of the (buffer, array) pairs hold its buffer's contents, with one
        wait for all (maps on a CPU device, copies otherwise)."""
        import pyopencl as cl

        pairs = [(buf, arr) for buf, arr in pairs if arr.size]
        if not pairs:
            self.queue.finish()
            return
        if not self.host_memory:
            for buf, arr in pairs[:-1]:
                cl.enqueue_copy(self.queue, arr, buf, is_blocking=False)
            cl.enqueue_copy(self.queue, pairs[-1][1], pairs[-1][0], is_blocking=True)
            return
        maps = []
        for buf, arr in pairs:
            mapped, event = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0, arr.shape, arr.dtype,
                                                  is_blocking=False)
            maps.append((mapped, arr))
        event.wait()  # an in-order queue: the last map done means all are
        for mapped, arr in maps:
            if mapped.__array_interface__["data"][0] != arr.__array_interface__["data"][0]:
                arr[...] = mapped  # the driver kept its own copy
            mapped.base.release()

    def release(self) -> None:
        """Drop the references to host arrays (call once the commands reading them are done)."""
        self.keep.clear()
