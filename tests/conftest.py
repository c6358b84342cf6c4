"""Shared fixtures: the ``device`` fixture runs a test on the CPU always and on cuda:0 when CUDA is present."""

from __future__ import annotations

import pytest
import warp as wp

from warpdem.cli import init_warp

init_warp()  # no banner, no "no CUDA driver" line on a CPU-only machine; warnings still show

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> str:
    """A Warp device name: "cpu", and "cuda:0" where CUDA is available."""
    return request.param
