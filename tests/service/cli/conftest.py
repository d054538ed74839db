"""Fixtures for the CLI tests: the real ``mcam`` console script in a subprocess."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.hdr_io import write_exr

MCAM = Path(sys.executable).parent / "mcam"
#: The issue's example flags: mantissa, alpha 2, 8 bits, 20 % of pixels over x = 1.
SIMULATE_FLAGS = ("--encoding", "mantissa", "--alpha", "2", "--bits", "8", "--overexposed", "0.2")


def run_mcam(*args: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run ``mcam ARGS`` in ``cwd``; stdout and stderr captured as text."""
    return subprocess.run(
        [str(MCAM), *(str(arg) for arg in args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def assert_one_line_error(result: subprocess.CompletedProcess[str], *fragments: str) -> None:
    """Exit code 2, one line on stderr holding every fragment, and no traceback."""
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("mcam "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0]


def blob_scene(
    size: int = 64, peak: float = 1000.0, halving: float = 3.0, rgb: bool = False
) -> np.ndarray:
    """A smooth blob ``peak * 2^(-r / halving)`` on a dim floor (r: pixels from the centre).

    Its log falls by ``1 / halving`` octaves per pixel, so with the issue's exposure a
    mantissa frame (alpha 2) wraps up to 6 times while neighbours differ by < 1/2 wrap.
    """
    yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2.0
    luma = 1e-3 + peak * 2.0 ** (-np.hypot(xx, yy) / halving)
    return np.stack([luma, luma * 0.7, luma * 0.4], axis=2) if rgb else luma


def mantissa_tolerance(reference: np.ndarray, gain: float, bits: int, alpha: float) -> np.ndarray:
    """Largest error of a mantissa reconstruction with the right W, in scene units.

    Half a code bin: ``2^-(bits+1)`` in x below saturation, a factor
    ``alpha^(2^-(bits+1))`` above; plus float32 rounding of both stored images.
    """
    x = reference * gain
    half_bin = 2.0 ** -(bits + 1)
    bound = np.where(x < 1.0, half_bin, x * (alpha**half_bin - 1.0)) / gain
    return bound + 2.0**-22 * reference


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder after ``mcam simulate`` and ``mcam reconstruct --decoder itoh`` on a blob.

    Holds scene.exr, wrapped.png, W_true.png, reference.exr, hdr.exr, W.png and
    the commands' stdout in simulate.out / reconstruct.out.
    """
    folder = tmp_path_factory.mktemp("pipeline")
    write_exr(folder / "scene.exr", blob_scene())
    simulate = run_mcam(
        "simulate", "scene.exr", "-o", "wrapped.png", *SIMULATE_FLAGS,
        "--ground-truth", "W_true.png", "--reference-out", "reference.exr",
        cwd=folder,
    )  # fmt: skip
    assert simulate.returncode == 0, simulate.stderr
    reconstruct = run_mcam(
        "reconstruct", "wrapped.png", "-o", "hdr.exr", "--decoder", "itoh",
        "--winding-out", "W.png",
        cwd=folder,
    )  # fmt: skip
    assert reconstruct.returncode == 0, reconstruct.stderr
    (folder / "simulate.out").write_text(simulate.stdout)
    (folder / "reconstruct.out").write_text(reconstruct.stdout)
    return folder
