"""Tests of ``mcam train`` (service/cli/train.py) through the real console script."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
from pathlib import Path

import onnxruntime as ort
import pytest
import torch

from models.training import config, losses, networks
from models.training.config import TrainConfig
from models.training.run_control import run_lock
from models.training.train import train
from service.cli.train import (
    LOSS_CHOICES,
    PRECISION_CHOICES,
    RISK_WEIGHT,
    TIER_CHOICES,
    Progress,
    reproduce,
)
from tests.service.cli.conftest import MCAM, assert_one_line_error, mcam_in_process, run_mcam


def test_train_run_then_export_makes_a_working_onnx_model(tmp_path: Path) -> None:
    trained = run_mcam(
        "train", "run", "--tier", "tiny", "--stages", "1,1,1", "--crop", "32", "--batch", "2",
        "--runs-dir", tmp_path / "runs", cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    assert "stage=3" in trained.stdout
    assert "[mantissanet-tiny-mantissa] step=3/3 " in trained.stdout
    assert trained.stdout.splitlines()[-2].endswith(" eta=0:00:00")
    checkpoint = tmp_path / "runs" / "mantissanet-tiny-mantissa" / "checkpoint.pt"
    exported = run_mcam(
        "train", "export", checkpoint, "--onnx-dir", tmp_path / "onnx", "--no-val", cwd=tmp_path
    )
    assert exported.returncode == 0 and "warning" not in exported.stderr, exported.stderr
    card = json.loads(exported.stdout.strip().splitlines()[-1])
    assert card["decoder"] == "mantissanet-tiny" and card["encoding"] == "mantissa"
    session = ort.InferenceSession(str(tmp_path / "onnx" / card["file"]))
    assert [i.name for i in session.get_inputs()] == ["m"]
    again = run_mcam(
        "train", "export", checkpoint, "--onnx-dir", tmp_path / "onnx", "--no-val", cwd=tmp_path
    )
    assert_one_line_error(again, "mantissanet-tiny-mantissa.onnx exists", "--force")
    card_path = tmp_path / "onnx" / f"{card['name']}.json"
    measured = run_mcam("train", "measure", card_path, cwd=tmp_path)
    assert measured.returncode == 0, measured.stderr
    stored = json.loads(card_path.read_text())
    plain = stored["val256"]["read_noise_0"]
    refined = stored["val256_refined"]["read_noise_0"]
    assert set(stored["val256"]) == {"read_noise_0", "read_noise_0.01"}
    assert 0 < plain["psnr"] < 100 and 0 < refined["psnr"] < 100
    assert refined["winding_accuracy"] > plain["winding_accuracy"]


def test_exporting_an_unfinished_run_warns(tmp_path: Path) -> None:
    config = TrainConfig(
        tier="tiny", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path / "runs"
    )
    checkpoint = train(config, deadline=0.0)  # stops after its first step
    exported = run_mcam(
        "train", "export", checkpoint, "--onnx-dir", tmp_path / "onnx", "--no-val", cwd=tmp_path
    )
    assert exported.returncode == 0, exported.stderr
    assert "warning:" in exported.stderr and "stopped at step 1 of 3" in exported.stderr


def test_train_run_trains_the_unmodnet_family(tmp_path: Path) -> None:
    """With the recipes' own options (the shipped unmodnet learns from its own states;
    ``mcam train run`` could not set them)."""
    trained = run_mcam(
        "train", "run", "--family", "unmodnet", "--tier", "tiny", "--stages", "1,1,1,1",
        "--crop", "32", "--large-crop", "48", "--batch", "4", "--own-states", "0.5",
        "--own-passes", "2", "--runs-dir", tmp_path / "runs", cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    checkpoint = tmp_path / "runs" / "unmodnet-tiny-mantissa" / "checkpoint.pt"
    saved = torch.load(checkpoint, weights_only=False)["config"]
    assert (saved["large_crop"], saved["own_states"], saved["own_passes"]) == (48, 0.5, 2)


def test_bad_stage_list_is_one_clear_line(tmp_path: Path) -> None:
    result = run_mcam("train", "run", "--stages", "10,x", cwd=tmp_path)
    assert_one_line_error(result, "--stages", "10,x")


def test_missing_checkpoint_is_one_clear_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    result = mcam_in_process(capsys, "train", "export", tmp_path / "nothing.pt")
    assert_one_line_error(result, "nothing.pt")


def test_missing_model_card_is_one_clear_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    result = mcam_in_process(capsys, "train", "measure", tmp_path / "nothing.json")
    assert_one_line_error(result, "nothing.json")


def test_the_command_line_offers_every_training_loss_tier_and_default() -> None:
    assert LOSS_CHOICES == losses.LOSSES
    assert TIER_CHOICES == tuple(networks.TIERS)
    assert RISK_WEIGHT == losses.RISK_WEIGHT
    assert PRECISION_CHOICES == config.PRECISIONS


@pytest.mark.parametrize(
    ("device", "message"),
    [("cuda", "no CUDA GPU"), ("gpu7", "torch device"), ("meta", "cpu or cuda[:N]"),
     ("mps", "cpu or cuda[:N]")],
)  # fmt: skip
def test_a_device_this_machine_lacks_is_one_clear_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], device: str, message: str
) -> None:
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    result = mcam_in_process(
        capsys, "train", "run", "--tier", "tiny", "--stages", "1,1,1", "--device", device,
        "--runs-dir", tmp_path / "runs",
    )  # fmt: skip
    assert_one_line_error(result, message)
    assert not (tmp_path / "runs").exists(), "a refused run left its folder behind"


@pytest.mark.parametrize(
    ("flags", "fragments"),
    [
        (("--batch", "0"), ("batch must be at least 1", "got 0")),
        (("--batch", "-3"), ("batch must be at least 1", "got -3")),
        (("--threads", "0"), ("threads must be at least 1", "got 0")),
        (("--threads", "-1"), ("threads must be at least 1", "got -1")),
        (("--seed", "-1"), ("seed must be in [0, 2**63)", "got -1")),
        (("--read-noise", "-1"), ("max read noise must be in [0, 1.0]", "got -1")),
        (("--read-noise", "5"), ("max read noise must be in [0, 1.0]", "got 5")),
        (("--crop", "512"), ("crop must be at most 256 px",)),
        (("--crop", "40"), ("crop must be a multiple of 16",)),
        (("--stages", "0,0,0"), ("stage steps (0, 0, 0) train nothing",)),
        # argparse took "-1,2,3" for an option: "expected one argument".
        (("--stages", "-1,2,3"), ("--stages takes 3 or 4", "got '-1,2,3'")),
        # str.isdigit took these: "²" ended in a ValueError traceback, "٥" ran as 5.
        (("--stages", "\u00b2,1,1"), ("--stages takes 3 or 4", "got '\u00b2,1,1'")),
        (("--stages", "\u0665,1,1"), ("--stages takes 3 or 4", "got '\u0665,1,1'")),
        (("--label", "a/b"), ("label must be one folder name", "'a/b'")),
        (("--init-from", "../x"), ("init_from must be one folder name",)),
        (("--own-states", "2"), ("own_states must be in [0, 1]", "got 2.0")),
        (("--own-passes", "0"), ("own_passes must be at least 1", "got 0")),
        (("--stages", "1,1,1,1", "--large-crop", "40"), ("large_crop must be a multiple",)),
    ],
    ids=lambda value: "_".join(value) if isinstance(value, tuple) else value,
)
def test_bad_run_settings_are_one_clear_line_before_training(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    flags: tuple[str, ...],
    fragments: tuple[str, ...],
) -> None:
    runs = tmp_path / "runs"
    result = mcam_in_process(
        capsys, "train", "run", "--stages", "1,1,1", *flags, "--runs-dir", runs
    )
    assert_one_line_error(result, "mcam train: error:", *fragments)
    assert not runs.exists()


def test_a_resume_with_other_settings_is_refused_naming_them(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    first = run_mcam(
        "train", "run", "--tier", "tiny", "--stages", "1,1,0", "--crop", "32", "--batch", "4",
        "--seed", "3", "--runs-dir", runs, cwd=tmp_path,
    )  # fmt: skip
    assert first.returncode == 0, first.stderr
    again = run_mcam(
        "train", "run", "--tier", "tiny", "--stages", "1,2,2,1", "--crop", "48", "--batch", "2",
        "--seed", "4", "--runs-dir", runs, cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(
        again, "trained with other settings", "stage_steps (1, 1, 0) (now (1, 2, 2, 1))",
        "crop 32 (now 48)", "batch 4 (now 2)", "seed 3 (now 4)", "--runs-dir", "--label",
    )  # fmt: skip
    checkpoint = runs / "mantissanet-tiny-mantissa" / "checkpoint.pt"
    assert torch.load(checkpoint, weights_only=False)["config"]["seed"] == 3


def start_training(runs: Path, cwd: Path) -> subprocess.Popen[str]:
    """``mcam train run`` of a long tiny run, once it has logged its first steps."""
    process = subprocess.Popen(
        [str(MCAM), "train", "run", "--tier", "tiny", "--stages", "1,100000,1", "--crop", "32",
         "--batch", "2", "--runs-dir", str(runs)],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert process.stdout is not None
    first = process.stdout.readline()
    assert "step=" in first, process.stderr.read() if process.stderr else first
    return process


def test_a_run_trained_by_another_process_is_refused_naming_it(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    holder = start_training(runs, tmp_path)
    try:
        second = run_mcam(
            "train", "run", "--tier", "tiny", "--stages", "1,100000,1", "--crop", "32",
            "--batch", "2", "--runs-dir", runs, cwd=tmp_path,
        )  # fmt: skip
        assert_one_line_error(second, f"being trained by process {holder.pid}", "wait")
    finally:
        holder.kill()
        holder.communicate()
    with run_lock(runs / "mantissanet-tiny-mantissa"):
        pass


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_saves_a_checkpoint_and_says_where_the_run_resumes(
    tmp_path: Path, signum: int, code: int
) -> None:
    runs = tmp_path / "runs"
    process = start_training(runs, tmp_path)
    process.send_signal(signum)
    _, err = process.communicate(timeout=120)
    assert process.returncode == code, err
    line = err.strip().splitlines()[-1]
    step = torch.load(
        runs / "mantissanet-tiny-mantissa" / "checkpoint.pt", weights_only=False
    )["step"]
    assert step >= 20 and line.startswith(f"mcam train: stopped by {signum.name}")
    assert f"after step {step} of 100002" in line and f"resume from step {step}" in line


def test_progress_lines_name_the_run_its_steps_and_the_time_left(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The first line's ETA is at the run's mean rate so far (a resumed run: 100 steps in
    50 s), later ones at this command's rate (20 steps in 20 s)."""
    progress = Progress("tiny-run", 1000)
    progress({"step": 100, "stage": 2, "loss": 0.5, "wall_s": 50.0})
    progress({"step": 120, "stage": 2, "loss": 0.25, "wall_s": 70.0})
    first, second = capsys.readouterr().out.splitlines()
    assert first == "[tiny-run] step=100/1000 stage=2 loss=0.5 wall_s=50 eta=0:07:30"
    assert second.startswith("[tiny-run] step=120/1000 stage=2")
    assert second.endswith(" eta=0:14:40")


def test_train_all_keeps_the_models_up_to_date_with_their_checkpoints(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A rerun exports, quantizes and measures only the runs whose checkpoint changed."""
    config = TrainConfig(
        tier="tiny", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path / "runs"
    )
    onnx_dir = tmp_path / "onnx"
    card_path = onnx_dir / "mantissanet-tiny-mantissa.json"
    reproduce([config], onnx_dir, measure=False)
    first = card_path.read_bytes()
    capsys.readouterr()
    reproduce([config], onnx_dir, measure=False)
    assert card_path.read_bytes() == first
    assert capsys.readouterr().out.startswith(f"up to date: {card_path}")
    shutil.rmtree(config.run_dir)
    reproduce([config], onnx_dir, measure=False)
    retrained = json.loads(card_path.read_text())["training"]["checkpoint_sha256"]
    assert retrained != json.loads(first)["training"]["checkpoint_sha256"]


@pytest.mark.parametrize("action", ["run", "export"])
def test_an_empty_checkpoint_is_one_clear_line(tmp_path: Path, action: str) -> None:
    checkpoint = tmp_path / "runs" / "mantissanet-tiny-mantissa" / "checkpoint.pt"
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"")
    if action == "run":
        args: tuple[str | Path, ...] = (
            "run", "--tier", "tiny", "--stages", "1,1,1", "--crop", "32", "--batch", "2",
            "--runs-dir", tmp_path / "runs",
        )  # fmt: skip
    else:
        args = ("export", checkpoint, "--onnx-dir", tmp_path / "onnx", "--no-val")
    result = run_mcam("train", *args, cwd=tmp_path)
    advice = "delete" if action == "run" else "training wrote"
    assert_one_line_error(result, f"{checkpoint} is not a readable checkpoint", advice)
    if action == "export":
        assert "delete" not in result.stderr
