"""Shared fixtures."""

import pytest

import instancing  # noqa: F401  (selects the Dr.Jit backend before Mitsuba loads)
from instancing.core.backend import BACKEND_NAME, MITSUBA_VARIANT, dr

import mitsuba as mi  # noqa: E402


@pytest.fixture(scope="module")
def mitsuba_backend_variant():
    """Mitsuba's variant of our backend for a test module; the previous variant restored after
    (other test modules select scalar_rgb at import)."""
    previous = mi.variant()
    mi.set_variant(MITSUBA_VARIANT)
    yield
    if previous is not None:
        mi.set_variant(previous)


@pytest.fixture
def one_thread():
    """Dr.Jit on one worker thread for the test (as INSTANCING_THREADS=1): runs are then
    bit-reproducible (with several threads, atomic float sums vary by a few ulps). On CUDA
    no setting fixes the order of float atomics: such a test is skipped there."""
    if BACKEND_NAME == "cuda":
        pytest.skip("needs bit-reproducible runs; CUDA's float atomics have no fixed order")
    previous = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(previous)
