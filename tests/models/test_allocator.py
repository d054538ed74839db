"""Tests of models/allocator.py: freed memory kept in the process heap."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from models.allocator import keep_freed_memory


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mallopt is glibc's")
def test_thresholds_are_set_and_setting_them_again_is_harmless() -> None:
    assert keep_freed_memory() is True
    assert keep_freed_memory() is True


def test_numpy_results_do_not_change_once_memory_is_kept() -> None:
    """A fresh process computes the same frame-sized results before and after (the
    heap serves blocks that mmap served before; contents are never assumed zero)."""
    script = textwrap.dedent(
        """
        import numpy as np
        from models.allocator import keep_freed_memory

        def work():
            rng = np.random.default_rng(0)
            total = 0.0
            for _ in range(20):
                a = rng.random((512, 512))
                total += float(np.maximum(a, a * 0.5 - 0.25).sum())
                total += float(np.empty((512, 512)).size)
            return total

        before = work()
        keep_freed_memory()
        print(before == work())
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=120
    )
    assert result.stdout.strip() == "True"


def test_the_command_line_keeps_freed_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    """``mcam`` calls it before parsing its arguments."""
    from service.cli import main as cli

    calls: list[bool] = []
    monkeypatch.setattr(cli, "keep_freed_memory", lambda: calls.append(True) or True)
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert calls == [True]
