"""Shared fixtures: every test must leave no thread behind (like ophyd-async's task check)."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import load_protocol, parse_protocol

ROOT = Path(__file__).resolve().parent.parent
PROTOCOLS = ROOT / "protocols"


# Modules whose tests run on the real clock (trials at speed 1, the daemon, the wire, soaks): they
# wait more than they compute, and what they measure (late ticks, a reply's timeout) is the
# machine's timing. Under pytest-xdist (`-n 2 --dist loadgroup`) they all go to one worker, one
# after another, and each has the machine to itself (`share_the_machine`); the analysis tests fill
# both workers the rest of the time.
CLOCK_MODULES = {
    "test_cli", "test_client", "test_control_path", "test_daemon", "test_daemon_workflow",
    "test_driver_bytes", "test_force_control", "test_install", "test_live", "test_logs",
    "test_loop_seams", "test_mbpoll", "test_model_loop", "test_ownership", "test_paced_wire",
    "test_ports", "test_preload", "test_probe", "test_recording_seams", "test_safety", "test_soak",
    "test_spy", "test_stop_anytime", "test_trial", "test_wire", "test_daemon_characterize", "test_pages_clock",
    "test_daemon_stops", "test_web", "test_calibrate", "test_newcomer",
}


def pytest_configure(config):
    if hasattr(config, "workerinput"):
        return
    # Hundreds of tests start `python -m rig` (the pages, the daemon, the simulated devices on the
    # wire), each importing the project from this tree. Where PYTHONDONTWRITEBYTECODE is set no
    # import caches its compiled code, so every process compiled every module again (0.1-0.2 s
    # each); compiled once here (into __pycache__, which git ignores), they read it, as an
    # installed package's processes do. A module edited afterwards is compiled afresh, as ever.
    import compileall

    for folder in ("rig", "drivers", "sim_device", "docs_build"):
        if (ROOT / folder).is_dir():
            compileall.compile_dir(ROOT / folder, quiet=2)


@pytest.hookimpl(tryfirst=True)  # before xdist's, which reads the group from the marker
def pytest_collection_modifyitems(config, items):
    # pytest-rerunfailures' flaky marker reruns on the host's evidence (absent, or -p no:rerunfailures: none)
    rerun = (pytest.mark.flaky(reruns=RERUNS, condition=_machine_was_taken)
             if config.pluginmanager.hasplugin("rerunfailures") else None)
    for item in items:
        if _on_the_clock(item):
            item.add_marker(pytest.mark.xdist_group("clock"))
            if rerun is not None:
                item.add_marker(rerun)
    if hasattr(config, "workerinput"):
        # the clock tests first, as one unit: they run back to back on one worker while the other
        # waits once, instead of each module of them waiting for an analysis test in progress
        items.sort(key=lambda item: not _on_the_clock(item))


def _on_the_clock(item) -> bool:
    return item.module.__name__.rpartition(".")[2] in CLOCK_MODULES


# A clock test has the machine to itself, but not the host under a virtual machine: a host that
# takes the virtual CPUs away (steal time, counted by the kernel in /proc/stat) delays ticks and
# pty bytes as no code of the rig can. A clock test that fails while the host took at least a
# tick's worth of time from this machine is run again (pytest-rerunfailures, reported as a rerun),
# at most RERUNS times and each time only on that evidence; its assertions are the same, and a
# failure with nothing taken fails. Two, because one was not enough in CI: test_live failed twice
# in a row, the second time with 1.7 s of CPU taken during its 12 s trial (two late ticks).
_STOLEN_AT: float | None = None
RERUNS = 2
STOLEN_MS = 10.0  # one clock tick of the kernel's accounting; a late tick is 5 ms


def stolen_ms() -> float | None:
    """CPU time the hypervisor took from this machine's virtual CPUs since boot (None: unknown)."""
    try:
        with open("/proc/stat") as fh:
            fields = fh.readline().split()  # cpu user nice system idle iowait irq softirq steal ...
        return int(fields[8]) * 1000.0 / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError, AttributeError):
        return None


def stolen_during_test_ms() -> float:
    """CPU time the host took from this machine since the running test's fixtures were up."""
    now = stolen_ms()
    return 0.0 if now is None or _STOLEN_AT is None else now - _STOLEN_AT


def _machine_was_taken() -> bool:
    return stolen_during_test_ms() >= STOLEN_MS


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    global _STOLEN_AT
    _STOLEN_AT = None  # never the last test's window
    yield
    _STOLEN_AT = stolen_ms()  # opened once the fixtures are up: a clock test has the machine by now


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed and _on_the_clock(item) and _STOLEN_AT is not None:
        report.sections.append(("machine", f"the host took {stolen_during_test_ms():.0f} ms of CPU from this "
                                           "virtual machine during the test (steal time, /proc/stat)"))


class _Machine:
    """Two flock(2) locks shared by the workers of one run: the machine (a clock test holds it
    alone, analysis tests together) and the intent to take it alone, which stops analysis tests
    from starting while a clock test waits, so it never waits for more than the test in progress.

    Measured without it: at nice 19 the computing worker still made two of four two-worker runs
    fail a clock test (a late tick in test_live, a second failed transaction in test_wire), the
    pseudo-terminal's bytes queued behind it. With it, a clock test sees the machine as a serial
    run gives it."""

    def __init__(self, run_id: str):
        import tempfile

        base = Path(tempfile.gettempdir()) / f"rig-pytest-{run_id}"
        self.machine = open(f"{base}.machine", "a")  # noqa: SIM115 (held for the worker's life)
        self.intent = open(f"{base}.intent", "a")  # noqa: SIM115
        self.alone = False

    def take_alone(self) -> None:
        import fcntl

        if not self.alone:
            fcntl.flock(self.intent, fcntl.LOCK_EX)
            fcntl.flock(self.machine, fcntl.LOCK_EX)
            self.alone = True

    def give_back(self) -> None:
        import fcntl

        if self.alone:
            fcntl.flock(self.machine, fcntl.LOCK_UN)
            fcntl.flock(self.intent, fcntl.LOCK_UN)
            self.alone = False

    @contextlib.contextmanager
    def shared(self):
        import fcntl

        fcntl.flock(self.intent, fcntl.LOCK_SH)
        fcntl.flock(self.machine, fcntl.LOCK_SH)
        fcntl.flock(self.intent, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(self.machine, fcntl.LOCK_UN)


_machine: _Machine | None = None


def _the_machine(config) -> _Machine | None:
    global _machine
    run_id = getattr(config, "workerinput", {}).get("testrunuid")
    if run_id and _machine is None:
        _machine = _Machine(run_id)
    return _machine


def _set_idle(idle: bool) -> None:
    os.sched_setscheduler(0, os.SCHED_IDLE if idle else os.SCHED_OTHER, os.sched_param(0))


def _idle_class() -> bool:
    """Can this worker move itself, and its children, to the idle scheduling class and back?"""
    try:
        _set_idle(True)
        _set_idle(False)
        return True
    except (AttributeError, OSError):
        return False


_IDLE = None


@pytest.fixture(autouse=True)
def share_the_machine(request):
    """Under pytest-xdist, a clock test runs with the machine to itself: it waits for the other
    worker's test in progress to end, and the other worker starts none until the clock tests
    that follow one another on this worker are done (`pytest_runtest_teardown`).

    RIG_TESTS_SHARE=idle instead runs every analysis test in Linux's idle scheduling class (with
    every process it starts), beside the clock tests: it takes a core only when no clock test's
    process wants one. Measured once on two cores: 1368 s for the suite against 1628 s, but a
    clock test failed (the daemon's soak over RTU in poll mode: the load cell silent for 103 ms,
    limit 100 ms), so it is not the default. The cause is the disk, not the processor: beside two
    idle-class processes that only compute, the same soak passes and a 1 ms sleep overshoots by
    4 ms at most; beside two that also write some 100 MB/s of files, its first position read
    timed out within seconds in 3 runs of 3. The idle class shares the processor, not the disk.
    With every temporary file in memory (a tmpfs) it still failed a suite run in two (a live-view
    trial faulted; a 4 ms reply counted a failed transaction), and two clock tests side by side,
    one a worker, failed too (a failed transaction too many, missed ticks): the clock tests run
    one at a time, alone."""
    global _IDLE
    machine = _the_machine(request.config)
    if machine is None:
        yield
        return
    if _IDLE is None:
        _IDLE = os.environ.get("RIG_TESTS_SHARE", "lock") == "idle" and _idle_class()
    clock = _on_the_clock(request.node)
    if clock and request.config.getvalue("loadgroup") and not request.node.nodeid.endswith("@clock"):
        # xdist's loadgroup names a group by a suffix to the node id; without it the clock
        # tests are spread over both workers and wait on each other for most of the run
        pytest.fail(f"pytest-xdist's --dist loadgroup did not group the clock tests (pytest "
                    f"{pytest.__version__}: no @clock on {request.node.nodeid}); install the "
                    "versions the test extra asks for: pip install '.[test]'")
    if _IDLE:
        _set_idle(not clock)
        yield
    elif clock:
        machine.take_alone()
        yield
    else:
        machine.give_back()
        with machine.shared():
            yield


def pytest_runtest_teardown(item, nextitem):
    # the machine is given back once the clock tests in a row on this worker are done
    if _machine is not None and (nextitem is None or not _on_the_clock(nextitem)):
        _machine.give_back()


@pytest.fixture(autouse=True)
def no_leaked_threads():
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    assert not leaked, f"test leaked threads: {[t.name for t in leaked]}"


def run_sim(protocol, config: RigConfig | None = None, tmp_path: Path | None = None,
            name: str = "trial.mcap", **opts):
    """Run a protocol (path, YAML text or Protocol) on the in-process simulated rig, virtual time."""
    config = config or RigConfig()
    if isinstance(protocol, str) and "\n" in protocol:
        proto = parse_protocol(protocol, "<test>")
    elif isinstance(protocol, str | Path):
        proto = load_protocol(protocol, config)
    else:
        proto = protocol
    log_path = (tmp_path or Path("/tmp")) / name
    return run_trial(proto, config, RunOptions(speed=0, progress=False, log_path=log_path, **opts))


@pytest.fixture(scope="session")
def paper_075_log(tmp_path_factory):
    """The paper's slowest protocol on the default simulated rig (shared: it is used a lot)."""
    tmp = tmp_path_factory.mktemp("paper")
    result = run_sim(PROTOCOLS / "paper-0.75mm_s.yaml", tmp_path=tmp)
    return result


# A calibration (a rate over five seeds, every named model on the longest records) runs whole
# under the benchmark (tests/bench/test_bench_full.py runs these tests with RIG_TESTS_FULL=1);
# the suite runs a part of it held to the same verdicts (the first seeds, the models that
# decide), so that a regression still fails the suite without the whole calibration in every run.
FULL = os.environ.get("RIG_TESTS_FULL") == "1"
SUITE_SEEDS = 2


def calibration_seeds(seeds: Iterable[int]) -> tuple[int, ...]:
    """`seeds` under the benchmark, else the first SUITE_SEEDS of them."""
    seeds = tuple(seeds)
    return seeds if FULL else seeds[:SUITE_SEEDS]


def per_seed(fn: Callable, seeds: Iterable, *args) -> list:
    """fn(seed, *args) for every seed, on every core: the seeds of a CPU-bound analysis test are
    independent and nothing here runs on the real clock. The workers are fresh processes (BLAS on
    one thread each, from the environment tests/__init__.py sets). Results in the order of
    `seeds`; a worker's exception is raised here."""
    seeds = list(seeds)
    # under pytest-xdist the other workers have their share of the cores
    share = (os.cpu_count() or 1) // max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), 1)
    workers = min(len(seeds), max(share, 1))
    if workers <= 1:
        return [fn(s, *args) for s in seeds]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(fn, seeds, *([a] * len(seeds) for a in args)))
