"""pytest plugin of scripts/gpu_check.sh: stop the test session cleanly at a deadline.

    GPU_CHECK_PYTEST_DEADLINE=<seconds since the epoch> python -m pytest -p gpu_check_pytest_deadline ...

After each test, once the deadline has passed, the session stops as after Ctrl-C would (exit code
2) but the report files, the JUnit XML among them, are still written with the tests that ran;
a `timeout` kill would leave none. Without the variable nothing changes.
"""
from __future__ import annotations

import os
import time

ENV_VAR = "GPU_CHECK_PYTEST_DEADLINE"


def deadline() -> float:
    """The deadline from ENV_VAR (time.time() seconds); infinity when unset or blank."""
    value = os.environ.get(ENV_VAR, "").strip()
    try:
        return float(value) if value else float("inf")
    except ValueError:
        raise ValueError(f"{ENV_VAR} must be seconds since the epoch, got {value!r}") from None


def pytest_configure(config):
    config.gpu_check_deadline = deadline()


def pytest_runtest_teardown(item, nextitem):
    if nextitem is not None and time.time() > item.config.gpu_check_deadline:
        item.session.shouldstop = f"{ENV_VAR} passed: the remaining tests were not run"
