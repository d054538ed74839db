"""Job records and their ids."""

from __future__ import annotations

import pytest

from worker.jobs import JobNotFoundError, validate_job_id


def test_an_id_in_capitals_is_told_that_ids_are_lower_case() -> None:
    """'5A08...' was told "job ids are 32 hexadecimal digits", which it is."""
    with pytest.raises(JobNotFoundError, match=r"32 hexadecimal digits in lower case \(0-9, a-f\)"):
        validate_job_id("5A" * 16)
    assert validate_job_id("5a" * 16) == "5a" * 16
