"""Shared test settings: a fixed seed; torch's idle threads told to sleep so PoCL gets the cores;
the kernel tests run once on every working OpenCL device (pyopencl's own tests do the same)."""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before anything imports torch

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import clgs  # noqa: E402,F401

#: Test modules whose every test runs on each working device: the OpenCL operators, their
#: torch ops and the training loop built on them. The rest run on the automatic choice.
KERNEL_TESTS = {
    "test_projector", "test_voxelizer", "test_tv_patch", "test_losses_cl", "test_field_sampler",
    "test_ct_projector", "test_ct_fdk", "test_ct_sart", "test_trainer", "test_vector_geometry",
    "test_ct_fdk_vectors", "test_operator_contract",
}


def _device_ids(devices):
    """Short, stable test ids: 'pocl', 'intel', 'nvidia', ... (with the platform index when two
    devices would share one)."""
    names = []
    for d in devices:
        p = d.platform.name.lower()
        short = "pocl" if "portable computing" in p else p.split("(")[0].split()[0].strip() or "device"
        names.append(short)
    return [n if names.count(n) == 1 else f"{n}{i}" for i, n in enumerate(names)]


def _working_devices():
    from clgs import runtime

    try:
        return runtime.working_devices()
    except runtime.NoOpenCLDevice:
        return []


def _device_report():
    """Which OpenCL devices the kernel tests run on, and which were left out and why."""
    from clgs import runtime

    lines = []
    try:
        for c in runtime.candidates():
            status = "kernel tests run here" if c.ok else f"not tested: {c.error}"
            lines.append(f"OpenCL {c.index} {c.label}: {status}")
    except runtime.NoOpenCLDevice as exc:
        lines.append(f"OpenCL: {exc}")
    found = " ".join(lines).lower()
    for name, key in (("PoCL", "portable computing"), ("Intel's CPU runtime", "intel(r) opencl")):
        if key not in found:
            lines.append(f"OpenCL: {name} is not installed here, so no kernel test runs on it "
                         "(bash setup.sh installs it)")
    return lines


def pytest_report_header(config):
    return _device_report()


#: device label -> {outcome: count} of the tests that ran on that device
_RAN_ON: dict = {}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Count each device-parametrised test's outcome under the device it really ran on."""
    outcome = yield
    report = outcome.get_result()
    dev = getattr(getattr(item, "callspec", None), "params", {}).get("cl_device")
    if dev is None or not (report.when == "call" or (report.when == "setup" and report.outcome != "passed")):
        return
    label = f"{dev.platform.name.strip()} | {dev.name.strip()}"
    counts = _RAN_ON.setdefault(label, {})
    counts[report.outcome] = counts.get(report.outcome, 0) + 1


def pytest_terminal_summary(terminalreporter):
    """The same report at the end, where ``pytest -q`` (which hides the header) shows it too,
    and what ran on each device."""
    for line in _device_report():
        terminalreporter.write_line(line)
    for label, counts in sorted(_RAN_ON.items()):
        figures = ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
        terminalreporter.write_line(f"kernel tests on {label}: {figures}")


def pytest_generate_tests(metafunc):
    if "cl_device" in metafunc.fixturenames and metafunc.module.__name__.rsplit(".", 1)[-1] in KERNEL_TESTS:
        devices = _working_devices()
        if devices:
            metafunc.parametrize("cl_device", devices, ids=_device_ids(devices), indirect=True, scope="module")


@pytest.fixture(scope="module", autouse=True)
def cl_device(request):
    """The OpenCL device a kernel test module runs on (each working one in turn); elsewhere the
    automatic choice. Module-scoped fixtures that build operators depend on it."""
    dev = getattr(request, "param", None)
    if dev is None:
        yield None
        return
    from clgs import runtime

    before = runtime.device()
    runtime.use_device(dev)
    try:
        yield dev
    finally:
        runtime.use_device(before)


@pytest.fixture
def cl_queue(cl_device):
    """A new in-order queue on the context of the device under test, to hand to an operator
    explicitly (``Op(..., queue=cl_queue)``)."""
    import pyopencl as cl

    from clgs import runtime

    return cl.CommandQueue(runtime.get_context())


@pytest.fixture
def cl_context(cl_device):
    """A context of its own on the device under test (not the process's), to hand to an operator
    explicitly (``Op(..., ctx=cl_context)``)."""
    import pyopencl as cl

    from clgs import runtime

    return cl.Context([runtime.device()])


@pytest.fixture(autouse=True)
def _keep_the_locale():
    """SimpleITK's DICOM writer (GDCM), which some tests use to make scanner-like series, sets the
    process's C locale and leaves it: Python's default text encoding then turns ASCII for every
    later test. Each test gets the locale it started with back."""
    import locale

    before = locale.setlocale(locale.LC_CTYPE)
    yield
    if locale.setlocale(locale.LC_CTYPE) != before:
        locale.setlocale(locale.LC_CTYPE, before)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def one_torch_thread():
    """Small tensors: one torch thread is faster (and steadier on a shared machine)."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
