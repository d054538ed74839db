"""Tests of bench/losses.py: a 3-step study of the four losses end to end (no timings)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import losses


def test_study_trains_exports_and_measures_every_loss(tmp_path: Path) -> None:
    out = tmp_path / "losses.json"
    losses.main(["--stages", "1,1,1", "--frames", "1", "--runs-dir", str(tmp_path / "runs"),
                 "--out", str(out)])  # fmt: skip
    report = json.loads(out.read_text())
    assert len(report["load_average"]) == 3 and report["machine"]["cores"] >= 1
    assert [row["loss"] for row in report["results"]] == ["ce", "ce-risk", "mse", "jumps"]
    for row in report["results"]:
        assert 0.0 <= row["read_noise_0"]["winding_accuracy"] <= 1.0
        assert (tmp_path / "runs" / "loss-study" / row["run"] / f"{row['run']}.onnx").exists()
    assert report["best"] in {"ce", "ce-risk", "mse", "jumps"}
    assert "| jumps |" in out.with_suffix(".md").read_text()


@pytest.mark.parametrize("stages", ["10,x", "-1,2,3"])
def test_bad_stages_are_refused_with_the_format(
    stages: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A stage list starting with a minus sign was taken for an option ("expected one
    argument"), and a bad one was "invalid parse_stages value", not what a list is."""
    with pytest.raises(SystemExit):
        losses.parse_args(["--stages", stages])
    assert "takes 3 or 4 comma-separated step counts" in capsys.readouterr().err


def test_more_frames_than_val256_has_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    """The study ran the 24 frames and its report said the count asked."""
    with pytest.raises(SystemExit) as exc:
        losses.parse_args(["--frames", "30"])
    assert exc.value.code == 2
    assert "--frames: val-256 has 24 frames, got 30; give 1 to 24" in capsys.readouterr().err
    assert losses.parse_args(["--frames", "24"]).frames == 24


def test_help_gives_the_whole_first_sentence(capsys: pytest.CaptureFixture[str]) -> None:
    """The description was the docstring's first line: "... (alone or plus the"."""
    with pytest.raises(SystemExit):
        losses.parse_args(["--help"])
    assert "(alone or plus the expected PSNR loss), MSE on W, MSE on jumps." in " ".join(
        capsys.readouterr().out.split()
    )
