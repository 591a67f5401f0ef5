"""Shared fixtures: small synthetic sequences with exact ground truth (no real data needed).

``python -m pytest -m "not slow"`` runs the quick suite (about 3 minutes on 2 cores); ``python -m pytest`` runs
everything (under 10 minutes). Mark a test ``@pytest.mark.slow`` when it takes seconds (see setup.cfg).
"""

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence
from tests.numba_cache_lock import serialise_numba_cache_saves

ROOT = Path(__file__).resolve().parents[1]
KERNEL_WARM_UP_LIMIT_S = 300
KERNEL_WARM_UP_MIN_SLOW_TESTS = 10  # below, the warm-up would cost a developer running a few tests more than it saves
_kernel_warm_up: tuple[subprocess.Popen, Path] | None = None
_slow_modules: set[Path] = set()

# The kernel warm-up compiles into the same cache while the first tests run.
serialise_numba_cache_saves()


def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    """The modules without slow tests first, each module's tests kept together and in order: the kernel warm-up
    (below) compiles while they run, and the whole runs of the slow modules then find the kernels compiled."""
    _slow_modules.update(item.path for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: item.path in _slow_modules)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Where many slow tests are selected, a second process compiles numba's kernels into its on-disk cache
    (tests/kernel_warm_up.py) while the first tests run on the other core: on a clean clone compiling takes minutes of
    one core, which the whole runs would otherwise wait for where each first needs a kernel."""
    global _kernel_warm_up
    if sum(item.get_closest_marker("slow") is not None for item in session.items) >= KERNEL_WARM_UP_MIN_SLOW_TESTS:
        folder = Path(tempfile.mkdtemp(prefix="tambridge_kernels_"))
        process = subprocess.Popen([sys.executable, "-m", "tests.kernel_warm_up", str(folder)], cwd=ROOT,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   env=dict(os.environ, PYTHONPATH=str(ROOT)))
        _kernel_warm_up = process, folder


def pytest_runtest_setup(item: pytest.Item) -> None:
    """The slow modules' whole runs start once the warm-up has finished: their subprocesses save into numba's cache
    without its lock."""
    if _kernel_warm_up is not None and item.path in _slow_modules:
        try:
            _kernel_warm_up[0].wait(timeout=KERNEL_WARM_UP_LIMIT_S)
        except subprocess.TimeoutExpired:
            _kernel_warm_up[0].kill()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if _kernel_warm_up is not None:
        process, folder = _kernel_warm_up
        process.kill()
        process.wait()
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def synthetic_sequence_dir(tmp_path_factory) -> Path:
    """A noise-free 30-frame 160x120 closed-loop sequence in the TUM layout (written once per session)."""
    folder = tmp_path_factory.mktemp("synthetic") / "room"
    write_synthetic_sequence(folder, SynthOptions(frame_count=30, width=160, height=120))
    return folder
