"""Shared fixtures: one OpenCL queue per test session (PYOPENCL_CTX or the default device)."""

from __future__ import annotations

import pytest

from plenocl.device import get_queue


@pytest.fixture(scope="session")
def queue():
    """A command queue on the chosen device (PoCL in CI); never skipped."""
    return get_queue()


@pytest.fixture(scope="session")
def small_camera():
    """A small, fast plenoptic camera: 12 x 10 lenses of ~17 px, M = 1, f/2 (matched)."""
    from helpers import lens_camera

    return lens_camera(12, 10)
