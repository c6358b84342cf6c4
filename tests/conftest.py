"""Shared fixtures: the ``device`` fixture runs a test on the CPU always and on cuda:0 when CUDA is present."""

from __future__ import annotations

import logging

import pytest
import warp as wp

wp.config.log_level = logging.WARNING  # no init banner; warnings still show
wp.init()

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> str:
    """A Warp device name: "cpu", and "cuda:0" where CUDA is available."""
    return request.param
