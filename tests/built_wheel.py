"""The checkout's wheel, built once a run, in the background from its start.

Its build compiles every kernel into the wheel (a minute and a half of one core). The run's
first process starts it beside its own warm-up (``conftest.pytest_configure``), which holds
only one core, so the wheel is built by the time ``tests/test_wheel.py`` asks for it, on a
core that was idle; its workers (pytest-xdist's processes) find it where
``VANTAGE_TEST_WHEEL`` says. Run alone, a test builds its own.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from service import ROOT

VARIABLE = "VANTAGE_TEST_WHEEL"  # the directory the run's wheel is built into
TEST_FILE = ROOT / "tests" / "test_wheel.py"


def start(paths: list[str]) -> subprocess.Popen | None:
    """Start building the wheel when ``paths`` (the run's arguments) take in ``test_wheel.py``;
    the build, for ``stop``, or None."""
    chosen = {Path(p.split("::")[0]).resolve() for p in paths}  # as pytest takes them: from here
    if not any(path == TEST_FILE or path in TEST_FILE.parents for path in chosen):
        return None
    where = Path(tempfile.mkdtemp(prefix="vantage-test-wheel-"))
    os.environ[VARIABLE] = str(where)  # the workers, started after, inherit it
    # Its output to a log and its exit status to a file of its own, written last: the workers
    # are not the build's parent
    script = '"$@" > "$0/log" 2>&1; echo $? > "$0/status.tmp" && mv "$0/status.tmp" "$0/status"'
    return subprocess.Popen(
        ["sh", "-c", script, str(where), *_command(where / "dist")], start_new_session=True
    )


def stop(build: subprocess.Popen | None) -> None:
    """The build stopped if it still runs, and its directory removed."""
    if build is None:
        return
    if build.poll() is None:
        os.killpg(build.pid, signal.SIGKILL)  # the shell and the build under it
        build.wait()
    shutil.rmtree(os.environ.pop(VARIABLE), ignore_errors=True)


def wheel(tmp_path: Path, timeout: float = 900) -> Path:
    """The run's wheel, once built; or one built now into ``tmp_path`` when no build was started.

    :raises AssertionError: with the build's output, if it failed or took past ``timeout`` s
    """
    where = os.environ.get(VARIABLE)
    if where is None:
        dist = tmp_path / "dist"
        done = subprocess.run(_command(dist), capture_output=True, text=True, timeout=timeout)
        assert done.returncode == 0, (
            f"the wheel's build failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        )
    else:
        dist, status = Path(where) / "dist", Path(where) / "status"
        deadline = time.monotonic() + timeout
        while not status.exists():
            assert time.monotonic() < deadline, f"the wheel's build ran past {timeout} s"
            time.sleep(0.5)
        log = (Path(where) / "log").read_text(errors="replace")
        assert status.read_text().strip() == "0", f"the wheel's build failed:\n{log[-6000:]}"
    (built,) = dist.glob("*.whl")
    return built


def _command(dist: Path) -> list[str]:
    return [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", str(ROOT), "-w", str(dist)]
