"""Every OpenCL operator follows one contract (clgs.runtime.Operator): it runs on the context and
queue it is given (the process's device by default), builds named program variants, launches
every kernel through the runtime's helper (which calls its ``on_launch`` hook), takes its buffers
from its own pool, and gives the same bits on an explicit queue or context as on the default."""
import ast
import importlib
import inspect
from pathlib import Path

import numpy as np
import pytest
import torch

from clgs import runtime
from clgs.geometry import Geometry, Grid

OPS = Path(__file__).resolve().parents[1] / "clgs" / "ops"


def _geometry(mode="cone"):
    return Geometry.default(n_views=3, mode=mode, n_voxel=8, n_detector=16, volume_mm=64.0)


def _scene(n=60, dtype=torch.float64):
    g = torch.Generator().manual_seed(3)
    means = (torch.rand(n, 3, generator=g) - 0.5).to(dtype)
    scales = (torch.rand(n, 3, generator=g) * 0.05 + 0.03).to(dtype)
    quats = torch.randn(n, 4, generator=g).to(dtype)
    rho = torch.rand(n, generator=g).to(dtype)
    return means, scales, quats, rho


def run_projector(op):
    from clgs.ops.voxelizer import cov_prec

    m, s, q, r = _scene()
    mats = cov_prec(s, q)[0].numpy()
    out = op.forward(m.numpy(), mats, r.numpy(), _geometry(), [0, 2], "affine")
    grads = op.backward(m.numpy(), mats, r.numpy(), _geometry(), [0, 2], "affine", out, token=op.last_token)
    return [out, *grads]


def run_voxelizer(op):
    from clgs.ops.voxelizer import pack_gaussians

    m, s, q, r = _scene()
    cov, prec, ext = op.cov_prec_forward(s, q, 7)
    gauss = pack_gaussians(m, prec, r, ext)
    grid = Grid((6, 7, 9), (-0.4, -0.4, -0.4), (0.1, 0.1, 0.1))
    field = op.grid_forward(gauss, grid)
    rows = op.grid_backward(gauss, grid, field, ("WANT_MEAN", "WANT_PREC", "WANT_RHO"))
    return [cov, prec, ext, field, rows]


def run_tv_patch(op):
    from clgs.ops.voxelizer import cov_prec

    m, s, q, r = _scene()
    _, prec, ext = cov_prec(s, q, cov=False, extent=True)
    grid = Grid((6, 7, 9), (-0.4, -0.4, -0.4), (0.1, 0.1, 0.1))
    value, idx, rows, field = op.forward(m, prec, r, ext, grid, ("WANT_MEAN", "WANT_PREC", "WANT_RHO"), field=True)
    return [np.float64(value), idx, rows, field]


def run_field_sampler(op):
    rng = np.random.default_rng(0)
    field = rng.random((2, 5, 6, 7))
    pts = np.zeros((3, 16))
    pts[:, :13] = rng.random((3, 13)) * 6 - 0.5
    values, cells = op.forward(field, pts)
    gout = np.zeros((2, 16))
    gout[:, :13] = rng.random((2, 13))
    return [values, cells, op.grad_points(field, pts, gout), op.grad_field(field.shape, pts, gout, cells, 13)]


def run_image_loss(op):
    rng = np.random.default_rng(1)
    a, b = rng.random((2, 12, 13)), rng.random((2, 12, 13))
    target = op.target(torch.from_numpy(b))
    terms = op.forward(a, target, grad=True)
    return [np.array(terms), op.backward(a, target, 1.0, 0.25, token=op.last_token)]


def run_ct_projector(op):
    vol = np.random.default_rng(2).random((8, 8, 8))
    proj = op.forward(vol)
    return [proj, op.backward(proj), op.backward(proj[1:], views=[1, 2])]


def run_fdk(op):
    g = _geometry()
    q = np.random.default_rng(3).random((g.n_views, *g.nDetector))
    return [op(q, g), op(q, g.as_vectors())]


#: operator class name -> (module, how to make one on (ctx, queue), a small call returning arrays)
CASES = {
    "GaussianProjector": ("projector", lambda ctx, q: _make("projector", "GaussianProjector", ctx=ctx, queue=q),
                          run_projector),
    "Voxelizer": ("voxelizer", lambda ctx, q: _make("voxelizer", "Voxelizer", ctx=ctx, queue=q), run_voxelizer),
    "PatchTV": ("tv_patch", lambda ctx, q: _make("tv_patch", "PatchTV", ctx=ctx, queue=q), run_tv_patch),
    "FieldSampler": ("field_sampler", lambda ctx, q: _make("field_sampler", "FieldSampler", ctx=ctx, queue=q),
                     run_field_sampler),
    "ImageLoss": ("ssim", lambda ctx, q: _make("ssim", "ImageLoss", ctx=ctx, queue=q), run_image_loss),
    "CTProjector": ("ct_projector", lambda ctx, q: _make("ct_projector", "CTProjector", _geometry(), ctx=ctx, queue=q),
                    run_ct_projector),
    "FDKBackprojector": ("fdk", lambda ctx, q: _make("fdk", "FDKBackprojector", ctx=ctx, queue=q), run_fdk),
}


def _make(module, name, *args, **kwargs):
    return getattr(importlib.import_module(f"clgs.ops.{module}"), name)(*args, **kwargs)


def _arrays(values):
    return [np.asarray(v.detach() if isinstance(v, torch.Tensor) else v) for v in values if v is not None]


def test_every_operator_class_has_a_contract_case():
    """Each subclass of clgs.runtime.Operator in clgs.ops that runs a kernel file (its own
    ``SOURCE``) is checked below (a new one needs a case; a shared base without a file needs none)."""
    found = set()
    for path in OPS.glob("*.py"):
        mod = importlib.import_module(f"clgs.ops.{path.stem}" if path.stem != "__init__" else "clgs.ops")
        found |= {name for name, obj in inspect.getmembers(mod, inspect.isclass)
                  if issubclass(obj, runtime.Operator) and obj is not runtime.Operator
                  and obj.__module__ == mod.__name__ and obj.SOURCE}
    assert found == set(CASES)


def test_operators_reach_opencl_only_through_the_runtime():
    """No module of clgs.ops imports pyopencl: launches, buffers and waits all go through
    clgs.runtime (the operator's ``launch``, its pool ``io``)."""
    users = []
    for path in OPS.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            users += [path.name for n in names if n.split(".")[0] == "pyopencl"]
    assert not users, f"modules of clgs.ops importing pyopencl: {sorted(set(users))}"


@pytest.mark.parametrize("name", sorted(CASES))
def test_explicit_queue_same_bits_and_every_launch_reported(name, cl_queue):
    import pyopencl as cl

    _, make, call = CASES[name]
    ctx = runtime.get_context()
    default = make(None, None)
    assert default.ctx is ctx and default.queue is runtime.get_queue()
    queue = cl_queue
    op = make(None, queue)  # the queue implies its context
    assert op.queue is queue and op.ctx == ctx and op.io.queue is queue
    launched = []
    op.on_launch = lambda kernel, event: launched.append((kernel, event))
    got, want = _arrays(call(op)), _arrays(call(default))
    assert launched and all(isinstance(e, cl.Event) for _, e in launched)
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


def test_an_explicit_context_is_the_one_used(cl_context):
    """Made on a context of its own, an operator builds its programs and buffers there, and a
    queue from another context is refused."""
    dev = runtime.device()
    ctx = cl_context
    op = _make("field_sampler", "FieldSampler", ctx=ctx)
    assert op.ctx is ctx and op.queue.context == ctx and op.queue.device == dev
    got = _arrays(run_field_sampler(op))
    want = _arrays(run_field_sampler(_make("field_sampler", "FieldSampler")))
    for a, b in zip(got, want):
        assert np.array_equal(a, b)
    prog = op._program(np.float64)
    assert prog.ctx is ctx
    assert op.io.scratch("sums", 64).context == ctx
    with pytest.raises(ValueError, match="another context"):
        _make("field_sampler", "FieldSampler", ctx=ctx, queue=runtime.get_queue())


def test_one_call_at_a_time_and_host_arrays_let_go(cl_device):
    """``call()`` holds the operator's lock (re-entrant) and drops the call's host arrays at its end."""
    op = _make("field_sampler", "FieldSampler")
    with op.call() as io:
        io.input(np.ones(8))
        with op.call():
            pass
        assert len(io.keep) == 1  # an inner call does not let go of the outer one's arrays
    assert not op.io.keep
