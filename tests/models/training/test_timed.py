"""Tests of models/training/timed.py: step plans sized by time, and one timed lane."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from models.training import timed
from models.training.checkpoints import load_checkpoint
from models.training.config import TrainConfig
from models.training.recipes import SHIPPED, TIMED_LANES

units = st.lists(
    st.lists(st.integers(0, 50), min_size=3, max_size=4).map(tuple), min_size=1, max_size=3
).filter(lambda chain: sum(map(sum, chain)) > 0)


@given(units, st.floats(0.5, 200.0), st.floats(10.0, 2000.0))
def test_plan_keeps_proportions_and_fits_the_time(
    chain: list[tuple[int, ...]], rate: float, seconds: float
) -> None:
    plan = timed.planned_steps(tuple(chain), rate, seconds)
    assert [len(run) for run in plan] == [len(run) for run in chain]
    for run, run_units in zip(plan, chain, strict=True):
        assert all((steps == 0) == (u == 0) for steps, u in zip(run, run_units, strict=True))
    stages = sum(u > 0 for run in chain for u in run)
    budget = (1 - timed.MARGIN) * seconds * rate
    assert sum(map(sum, plan)) <= budget + stages
    assert sum(map(sum, plan)) >= budget - stages


@pytest.mark.parametrize(
    ("rate", "seconds", "message"), [(0.0, 10.0, "positive rate"), (1.0, -1.0, "positive")]
)
def test_plan_refuses_no_rate_or_no_time(rate: float, seconds: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        timed.planned_steps(((1, 1, 1),), rate, seconds)


def test_plan_refuses_a_chain_without_steps() -> None:
    with pytest.raises(ValueError, match="at least one stage"):
        timed.planned_steps(((0, 0, 0),), 1.0, 10.0)


@pytest.mark.parametrize("name", sorted(TIMED_LANES))
def test_lanes_start_from_scratch_a_shipped_run_a_lane_run_or_their_own_chain(
    name: str,
) -> None:
    laned = {config.name for chains in TIMED_LANES.values() for c in chains for config in c}
    known = {config.name for config in SHIPPED} | laned
    for chain in TIMED_LANES[name]:
        assert chain[0].init_from is None or chain[0].init_from in known
        names = [config.name for config in chain]
        assert len(set(names)) == len(names)
        for before, config in zip(chain, chain[1:], strict=False):
            assert config.init_from == before.name


def test_a_lane_probes_plans_and_trains_its_chain_before_the_deadline(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(timed, "PROBE_FROM", 1.0)
    monkeypatch.setattr(timed, "PROBE_TO", 4.0)
    first = TrainConfig(
        tier="tiny", stage_steps=(1, 2, 2, 1), crop=32, large_crop=32, batch=2,
        runs_dir=tmp_path, workers=1, precision="bf16",
    )  # fmt: skip
    noisy = replace(first, stage_steps=(0, 0, 0, 1), max_read_noise=0.02, init_from=first.name)
    started = time.monotonic()
    checkpoints = timed.run_lane((first, noisy), started, started + 9.0)
    states = [load_checkpoint(path) for path in checkpoints]
    planned = [tuple(state["config"]["stage_steps"]) for state in states]
    assert planned[0][0] >= 1 and planned[1][:3] == (0, 0, 0)
    assert planned[1][3] == planned[0][3] and sum(planned[0]) > 20
    assert [state["config"]["precision"] for state in states] == ["bf16", "bf16"]
    # Each run trains its plan, unless the deadline (a guard for a mis-probed rate) cuts it.
    assert all(1 <= s["step"] <= sum(p) for s, p in zip(states, planned, strict=True))
    assert states[1]["config"]["init_from"] == first.name
    assert not list(tmp_path.glob("*probe*"))


def test_a_lane_whose_deadline_passes_during_its_probe_trains_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The probe ends after the first step past its window, so a deadline at the
    window's end has passed when the plan is made: no run starts."""
    monkeypatch.setattr(timed, "PROBE_FROM", 0.5)
    monkeypatch.setattr(timed, "PROBE_TO", 2.0)
    config = TrainConfig(tier="tiny", stage_steps=(1, 1, 1, 1), crop=32, large_crop=32,
                         batch=2, runs_dir=tmp_path, workers=1)
    started = time.monotonic()
    assert timed.run_lane((config,), started, started + timed.PROBE_TO) == []
    assert "took all the time" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []


def test_a_probe_without_steps_in_its_window_says_why(tmp_path: Path) -> None:
    config = TrainConfig(tier="tiny", crop=32, batch=2, runs_dir=tmp_path)
    now = time.monotonic()
    with pytest.raises(RuntimeError, match="fewer than 2 probe steps ended in any of 3"):
        timed.probe_rate(config, (now - 30.0, now - 20.0))


def test_a_probe_measures_the_next_window_after_a_slow_start(tmp_path: Path) -> None:
    """A window that ended before the probe started (a start-up longer than the window)
    is measured again one window later."""
    config = TrainConfig(tier="tiny", crop=32, batch=2, runs_dir=tmp_path)
    now = time.monotonic()
    assert timed.probe_rate(config, (now - 3.0, now)) > 0  # no step ends in the first


def test_an_unknown_lane_set_is_refused_with_the_known_ones(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        timed.main(["--lanes", "nope", "--device", "cpu"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert "invalid choice: 'nope'" in error and "s2d" in error


@pytest.mark.parametrize(
    ("option", "message"),
    [(["--workers", "-1"], "workers must be >= 0"), (["--seconds", "0"], "--seconds must be"),
     (["--seconds", "nan"], "--seconds must be")],
)
def test_bad_settings_are_refused_before_any_lane_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, option: list[str], message: str
) -> None:
    """Each lane's process failed with a traceback of its own (with the default
    --device cuda, on every machine without a GPU)."""
    with pytest.raises(SystemExit) as exit_info:
        timed.main(["--lanes", "large", "--device", "cpu", "--runs-dir", str(tmp_path), *option])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
