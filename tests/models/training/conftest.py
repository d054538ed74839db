"""Shared fixture of the training tests: a 3-step tiny run, exported to ONNX."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.training.config import TrainConfig
from models.training.export import export_run
from models.training.train import train


@pytest.fixture(scope="session")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(checkpoint, card path) of a tiny mantissa run trained for 3 steps."""
    root = tmp_path_factory.mktemp("export")
    config = TrainConfig(tier="tiny", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=root)
    checkpoint = train(config)
    return checkpoint, export_run(checkpoint, root / "onnx")
