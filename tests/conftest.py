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
# wait more than they compute. Under pytest-xdist (`-n 2 --dist loadgroup`, the project's
# default) they all go to one worker, one after another, so two of them never share the machine's
# timing, while the other worker computes; the analysis tests fill both.
CLOCK_MODULES = {
    "test_cli", "test_client", "test_control_path", "test_daemon", "test_daemon_workflow",
    "test_driver_bytes", "test_force_control", "test_install", "test_live", "test_logs",
    "test_loop_seams", "test_mbpoll", "test_model_loop", "test_ownership", "test_paced_wire",
    "test_ports", "test_preload", "test_probe", "test_recording_seams", "test_safety", "test_soak",
    "test_spy", "test_stop_anytime", "test_trial", "test_wire",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.module.__name__.rpartition(".")[2] in CLOCK_MODULES:
            item.add_marker(pytest.mark.xdist_group("clock"))


@pytest.fixture(autouse=True)
def share_the_machine(request):
    """Under pytest-xdist, a worker computing gives way to one on the clock: the computing one
    runs at nice 19 (the least share the scheduler gives), so the kernel's threads that pass a
    pseudo-terminal's bytes on (at normal priority) are not queued behind it. Back to 0 for a
    clock test (allowed as root, as in CI; elsewhere the worker stays where it is)."""
    if "PYTEST_XDIST_WORKER" in os.environ:
        want = 0 if request.node.get_closest_marker("xdist_group") else 19
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, want)
    yield


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
