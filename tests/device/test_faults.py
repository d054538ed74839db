"""Fault injection switches: which values a run can be made with."""

from __future__ import annotations

import math

import pytest

from device.faults import Faults
from models.errors import InvalidInputError


@pytest.mark.parametrize("name", ["stall_s", "disconnect_s"])
@pytest.mark.parametrize("value", [-1.0, math.nan, math.inf, 1e12])
def test_a_fault_duration_must_be_finite_seconds(name: str, value: float) -> None:
    """1e12 s was taken, and the camera's thread died of an OverflowError in
    ``time.sleep`` at its first stall or disconnect: a traceback, then no frame."""
    with pytest.raises(InvalidInputError, match=f"{name} must be a finite number of seconds, "
                                                "0 to 3600, got"):
        Faults(**{name: value})


@pytest.mark.parametrize("name", ["stall_every", "disconnect_every"])
@pytest.mark.parametrize("value", [-1, 2.5, True])
def test_a_fault_period_must_be_a_whole_number_of_packets(name: str, value: object) -> None:
    with pytest.raises(InvalidInputError, match=f"{name} must be a whole number of packets"):
        Faults(**{name: value})


def test_zero_periods_and_durations_mean_no_fault() -> None:
    faults = Faults(stall_every=0, stall_s=0.0, disconnect_every=0, disconnect_s=0.0)
    assert not any(faults.stall_now(i) or faults.disconnect_now(i) for i in range(10))
