"""Settings shared by the whole suite.

Hypothesis tests run without a per-example deadline: CI runs on two shared cores, where
a garbage collection or a stolen time slice can stretch one example past the default
200 ms and fail a correct test. Tests never assert timings (``bench/`` measures them).
"""

from __future__ import annotations

from hypothesis import settings

settings.register_profile("mcam", deadline=None)
settings.load_profile("mcam")
