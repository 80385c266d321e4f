"""Device choice by probe, clgs info, the ICD registration of Intel's runtime, and the kernels
agreeing across OpenCL implementations (every working device against the first)."""
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from clgs import runtime
from clgs.cli import main
from clgs.runtime import devices, drivers

WORKING = runtime.working_devices()


@pytest.fixture
def fresh_choice(monkeypatch):
    """The runtime's choice and probe records as if nothing had been chosen yet (restored after)."""
    monkeypatch.setattr(devices, "_current", None)
    monkeypatch.setattr(devices, "_probes", dict(devices._probes))
    monkeypatch.delenv("CLGS_DEVICE", raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    yield
    devices._current = None


def _fail(monkeypatch, failing, reason="error: unknown target CPU 'generic'"):
    """Make the probe fail, with ``reason``, on every device in ``failing``."""
    for d in failing:
        devices._probes[d.int_ptr] = reason


def test_every_listed_device_has_a_probe_result_on_one_line():
    found = runtime.candidates()
    assert found, "no OpenCL device listed at all"
    for c in found:
        assert c.error is None or (c.error and "\n" not in c.error and len(c.error) <= 200)
    assert [c.device for c in found if c.ok] == WORKING
    assert WORKING, "no device passes the probe: " + "; ".join(f"{c.label}: {c.error}" for c in found)


def test_probe_kernel_results_are_checked(fresh_choice):
    # the probe compares 2^t with NumPy: a device giving wrong numbers fails it
    assert devices.probe(WORKING[0]) is None
    log = "x\n  error: unknown target CPU 'generic'\nmore"
    assert devices._first_line(log) == "error: unknown target CPU 'generic'"
    assert devices._first_line("") == "unknown failure"


def test_a_failing_device_is_skipped_and_its_reason_kept(fresh_choice, monkeypatch):
    preferred = sorted(devices._listed(), key=devices._preference)
    first = preferred[0][1]
    _fail(monkeypatch, [first])
    if len(preferred) == 1:
        with pytest.raises(runtime.NoOpenCLDevice) as err:
            runtime.device()
        assert "unknown target CPU" in str(err.value) and "pocl-opencl-icd" in str(err.value)
        return
    chosen = runtime.device()
    assert chosen.int_ptr != first.int_ptr
    assert chosen.int_ptr == next(d for _, d in preferred[1:] if devices.probe(d) is None).int_ptr


def test_no_working_device_says_why_and_what_to_install(fresh_choice, monkeypatch):
    _fail(monkeypatch, [d for _, d in devices._listed()])
    with pytest.raises(runtime.NoOpenCLDevice) as err:
        runtime.get_context()
    text = str(err.value)
    assert "unknown target CPU 'generic'" in text
    assert "setup.sh" in text and "pocl-opencl-icd" in text and "intel-opencl-rt" in text
    assert "Traceback" not in text


def test_an_explicit_choice_wins_and_a_failing_one_is_an_error(fresh_choice, monkeypatch):
    last = devices.candidates()[-1]
    monkeypatch.setenv("CLGS_DEVICE", last.index)
    assert runtime.device().int_ptr == last.device.int_ptr
    devices._current = None
    _fail(monkeypatch, [last.device], "error: no such builtin")
    with pytest.raises(runtime.NoOpenCLDevice, match="CLGS_DEVICE=.*no such builtin"):
        runtime.device()


def test_pyopencl_ctx_is_honoured_and_clgs_device_wins_over_it(fresh_choice, monkeypatch):
    found = devices.candidates()
    monkeypatch.setenv("PYOPENCL_CTX", found[-1].index)
    assert runtime.device().int_ptr == found[-1].device.int_ptr
    devices._current = None
    monkeypatch.setenv("CLGS_DEVICE", found[0].index)
    assert runtime.device().int_ptr == found[0].device.int_ptr


@pytest.mark.parametrize("spec, message", [
    ("99", "no platform 99"), ("0:99", "has no device 99"), ("no-such-driver", "no OpenCL device matches"),
])
def test_bad_device_specs_are_clear_errors(fresh_choice, spec, message):
    with pytest.raises(runtime.NoOpenCLDevice, match=message):
        runtime.use_device(spec)
    assert os.environ.get("CLGS_DEVICE") is None  # a refused choice leaves nothing behind


def test_a_device_is_named_by_a_piece_of_its_name(fresh_choice):
    c = devices.candidates()[0]
    piece = c.name.strip()[-6:].lower()
    assert devices._matching(piece)[0][1].int_ptr in {d.int_ptr for _, d in devices._listed()}
    assert devices._matching(c.index)[0][1].int_ptr == c.device.int_ptr


def test_clgs_info_marks_failing_devices_with_their_reason_and_the_choice(fresh_choice, monkeypatch):
    listed = [d for _, d in devices._listed()]
    if len(listed) < 2:
        pytest.skip("one OpenCL device listed: nothing to fail over to")
    first = sorted(devices._listed(), key=devices._preference)[0][1]
    _fail(monkeypatch, [first], "error: unknown target CPU 'generic'")
    out = CliRunner().invoke(main, ["info"])
    assert out.exit_code == 0, out.output
    lines = out.output.splitlines()
    failing = [ln for ln in lines if "FAILS: error: unknown target CPU 'generic'" in ln]
    assert len(failing) == 1 and first.name.strip() in failing[0] and not failing[0].lstrip().startswith("*")
    chosen = [ln for ln in lines if ln.startswith(" * ")]
    assert len(chosen) == 1 and "| works" in chosen[0]
    assert any(ln.startswith("chosen: ") for ln in lines)


def test_clgs_device_option_sets_the_choice_and_rejects_unknown_devices(fresh_choice):
    spec = devices.candidates()[-1].index
    out = CliRunner().invoke(main, ["--device", spec, "info"])
    assert out.exit_code == 0, out.output
    chosen = [ln for ln in out.output.splitlines() if ln.startswith(" * ")]
    assert len(chosen) == 1 and f" {spec} " in chosen[0]
    os.environ.pop("CLGS_DEVICE", None)
    devices._current = None
    out = CliRunner().invoke(main, ["--device", "no-such-driver", "info"])
    assert "no OpenCL device matches 'no-such-driver'" in out.output
    assert out.exit_code == 1  # a set-up script stops here
    os.environ.pop("CLGS_DEVICE", None)


def _clgs(args, env_extra, cwd):
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # this checkout's clgs
    env = {**os.environ, **env_extra, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    env.pop("CLGS_DEVICE", None)
    return subprocess.run([sys.executable, "-m", "clgs.cli", *args], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=300)


def test_no_opencl_at_all_is_one_message_and_a_failing_status(tmp_path):
    """No platform (the ICD loader finds no driver): `clgs info` exits 1, and a reconstruction says
    so in one message, not a traceback, before any work."""
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan

    g = Geometry.default(n_views=4, mode="parallel", n_detector=16, n_voxel=16)
    Scan(g, np.zeros(g.projection_shape, np.float32)).save(tmp_path / "scan")
    none = {"OCL_ICD_VENDORS": str(tmp_path / "no-drivers"), "OCL_ICD_FILENAMES": ""}
    res = _clgs(["info"], none, tmp_path)
    assert res.returncode == 1 and "No OpenCL platform found" in res.stdout + res.stderr
    res = _clgs(["reconstruct", "scan", "--method", "fdk", "--out", "fdk"], none, tmp_path)
    text = res.stdout + res.stderr
    assert res.returncode == 1 and "Traceback" not in text and "OpenCL" in text, text
    assert not (tmp_path / "fdk").exists()
    res = _clgs(["--device", "no-such-driver", "reconstruct", "scan", "--method", "fdk", "--out", "fdk"], {},
                tmp_path)
    text = res.stdout + res.stderr
    assert res.returncode == 1 and "Traceback" not in text and "no-such-driver" in text, text


# ------------------------------------------------------------------ Intel's runtime from PyPI
def test_intel_runtime_registration_keeps_system_drivers(tmp_path, monkeypatch):
    system = tmp_path / "vendors"
    system.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    (system / "broken-intel.icd").write_text("/opt/nowhere/libintelocl.so\n")
    lib = tmp_path / "lib" / "libintelocl.so"
    lib.parent.mkdir()
    lib.write_bytes(b"")
    monkeypatch.setattr(drivers, "intel_cpu_library", lambda: lib)
    monkeypatch.setenv("OPENCL_VENDOR_PATH", str(system))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("OCL_ICD_VENDORS", raising=False)
    folder = drivers.register_intel_cpu_runtime()
    assert folder is not None and os.environ["OCL_ICD_VENDORS"] == str(folder)
    assert folder.is_relative_to(tmp_path / "cache")
    icds = {p.name: p.read_text().strip() for p in folder.glob("*.icd")}
    assert icds == {"pocl.icd": "libpocl.so.2", "clgs-intel-cpu.icd": str(lib)}
    assert not list(folder.glob(".tmp-*"))
    # the same drivers give the same folder (processes started at once agree); a user's choice wins
    monkeypatch.delenv("OCL_ICD_VENDORS")
    assert drivers.register_intel_cpu_runtime() == folder
    monkeypatch.setenv("OCL_ICD_VENDORS", "/my/own")
    assert drivers.register_intel_cpu_runtime() is None and os.environ["OCL_ICD_VENDORS"] == "/my/own"


def test_intel_runtime_absent_means_nothing_registered(monkeypatch):
    monkeypatch.setattr(drivers, "intel_cpu_library", lambda: None)
    monkeypatch.delenv("OCL_ICD_VENDORS", raising=False)
    assert drivers.register_intel_cpu_runtime() is None
    assert "OCL_ICD_VENDORS" not in os.environ


def test_installed_intel_runtime_is_found_where_pip_put_it():
    lib = drivers.intel_cpu_library()
    if lib is None:
        pytest.skip("intel-opencl-rt is not installed (it is a dependency on x86-64 Linux only)")
    assert lib.name == "libintelocl.so" and lib.is_file()


# ------------------------------------------------------------------ agreement across drivers
def _kernels_on(dev):
    """Every operator's float32 results on ``dev`` for one fixed scene."""
    from clgs.geometry import Geometry
    from clgs.ops.ct_projector import CTProjector
    from clgs.ops.projector import project
    from clgs.ops.ssim import default_image_loss, l1_dssim
    from clgs.ops.voxelizer import voxelize

    runtime.use_device(dev)
    geo = Geometry.default(n_views=4, n_voxel=24, n_detector=40, volume_mm=64.0)
    g = torch.Generator().manual_seed(3)
    n = 400
    m = (torch.rand(n, 3, generator=g) * 1.2 - 0.6).requires_grad_()
    s = (torch.rand(n, 3, generator=g) * 0.06 + 0.02).requires_grad_()
    q = torch.randn(n, 4, generator=g).requires_grad_()
    d = (torch.rand(n, generator=g) * 0.02 + 0.005).requires_grad_()
    out = {}
    for mode in ("affine", "exact"):
        img = project(m, s, q, d, geo, [0, 1, 2, 3], mode=mode)
        w = torch.rand(img.shape, generator=torch.Generator().manual_seed(5))
        grads = torch.autograd.grad((img * w).sum(), (m, s, q, d))
        out[f"project {mode}"] = img.detach().numpy()
        for name, gr in zip("msqd", grads):
            out[f"project {mode} d/d{name}"] = gr.numpy()
    vol = voxelize(m, s, q, d, geo.volume_grid())
    grads = torch.autograd.grad((vol * vol).sum(), (m, s, q, d))
    out["voxelize"] = vol.detach().numpy()
    for name, gr in zip("msqd", grads):
        out[f"voxelize d/d{name}"] = gr.numpy()
    truth = vol.detach().numpy().astype(np.float32)
    ct = CTProjector(geo)
    sino = ct.forward(truth)
    out["ct forward"] = sino
    out["ct backward"] = ct.backward(sino)
    a = torch.rand(2, 40, 40, generator=torch.Generator().manual_seed(6), requires_grad=True)
    b = torch.rand(2, 40, 40, generator=torch.Generator().manual_seed(7))
    l1, dssim = l1_dssim(a, default_image_loss().target(b))
    out["l1, d-ssim"] = np.array([float(l1.detach()), float(dssim.detach())])
    out["l1 + d-ssim grad"] = torch.autograd.grad(l1 + 0.25 * dssim, a)[0].numpy()
    return out


@pytest.mark.skipif(len(WORKING) < 2, reason="one working OpenCL device: nothing to compare")
def test_every_kernel_agrees_across_opencl_implementations():
    """The same float32 scene on every working device: results agree with the first device's to
    within float32 rounding of sums of a few hundred terms (relative to each output's scale), and
    each device gives the same bits when asked twice."""
    before = runtime.device()
    try:
        ref = _kernels_on(WORKING[0])
        for dev in WORKING[1:]:
            got = _kernels_on(dev)
            again = _kernels_on(dev)
            for key, want in ref.items():
                scale = float(np.abs(want).max())
                assert scale > 0, key
                err = float(np.abs(got[key] - want).max()) / scale
                assert err < 2e-5, f"{key}: {devices.device_label(dev)} differs by {err:.2e} of its scale"
                assert np.array_equal(got[key], again[key]), f"{key}: not the same bits twice on {dev.name}"
    finally:
        runtime.use_device(before)
