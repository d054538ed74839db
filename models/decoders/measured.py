"""Measured figures of each decoder and where they come from (``GET /v1/decoders``).

A learned decoder's figures are its model cards' (:func:`models.decoders.learned.figures`:
size, cost and the val-256 metrics measured at export). Decoders without a card
(classical, refined ``+puma``, adaptive ``auto*``) take their rows of the val-256
benchmark, ``bench/results/accuracy.json`` (``python -m bench.accuracy``), in the cards'
shape: ``{encoding: {"val256": {"read_noise_<sigma>": {metric: value}}}}``. A decoder
measured by neither has no figures, and its source says so and where to look: that file
is part of a repository checkout, not of an installed package (the service reads a copy
named by ``MCAM_ACCURACY_REPORT``; the Docker image ships one and names it).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from models.decoders.registry import DecoderSpec

log = logging.getLogger(__name__)

#: The repository's root folder.
ROOT = Path(__file__).resolve().parents[2]
#: The val-256 benchmark's report (written by ``python -m bench.accuracy``).
ACCURACY_REPORT = ROOT / "bench" / "results" / "accuracy.json"
#: The benchmark's metrics a card also states (accuracy a fraction, PSNRs in dB, time in ms).
METRICS = ("winding_accuracy", "psnr", "pu21_psnr", "ssim", "ms_ssim", "ms_per_frame")


@dataclass(frozen=True)
class BenchmarkFigures:
    """The val-256 figures of a benchmark report, by decoder name; the report's file
    (relative to the repository) and a description of the run."""

    by_decoder: dict[str, dict[str, Any]]
    report: str
    source: str


def _metrics(row: dict[str, Any]) -> dict[str, float]:
    """A report row's metrics, rounded as the cards round them (4 decimals, ms to 2)."""
    return {name: round(float(row[name]), 2 if name == "ms_per_frame" else 4) for name in METRICS}


def _figures(report: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per decoder, per encoding, per read-noise level (sigma in wraps): the metrics of
    every measured row (the main table at no noise, the noise table above it)."""
    rows = [{**row, "read_noise": 0.0} for row in report["results"]]
    rows += [row for row in report.get("noise", {}).get("results", []) if row["read_noise"] > 0]
    found: dict[str, dict[str, Any]] = {}
    for row in rows:
        if "psnr" not in row:  # a decoder without a model for that encoding: not measured
            continue
        val256 = found.setdefault(row["decoder"], {}).setdefault(row["encoding"], {"val256": {}})
        val256["val256"][f"read_noise_{row['read_noise']:g}"] = _metrics(row)
    return found


#: What reading a report raises when it gives no figures: no file, or one that cannot be
#: read (OSError), or not a complete report.
REPORT_ERRORS = (OSError, ValueError, KeyError, TypeError, AttributeError)


@cache
def benchmark_figures(path: Path = ACCURACY_REPORT) -> BenchmarkFigures | None:
    """The figures of the val-256 benchmark report at ``path``; None when there is none
    or it cannot be read (logged once: the result is cached)."""
    try:
        return _read_report(path)
    except FileNotFoundError:
        return None
    except REPORT_ERRORS as exc:
        log.warning(
            "%s, so decoders without a model card show no figures; make it readable or "
            "rerun python -m bench.accuracy to write it again",
            _problem(path, exc),
        )
        return None


def report_problem(path: Path) -> str | None:
    """Why the report at ``path`` would give no figures (no file, a directory, a file
    that cannot be read or is not a complete val-256 report); None when it gives them.
    Read afresh, not cached: for a setting that names the report."""
    try:
        _read_report(path)
    except REPORT_ERRORS as exc:
        return _problem(path, exc)
    return None


def _problem(path: Path, exc: Exception) -> str:
    """What ``exc``, raised reading the report at ``path``, says is wrong with it."""
    if isinstance(exc, FileNotFoundError):
        return f"no file at {path}"
    if isinstance(exc, IsADirectoryError):
        return f"{path} is a directory, not a report"
    if isinstance(exc, OSError):
        return f"cannot read {path} ({exc.strerror or exc})"
    return f"{path} is not a complete val-256 benchmark report ({type(exc).__name__}: {exc})"


def _read_report(path: Path) -> BenchmarkFigures:
    """The figures of the report at ``path``; raises what reading or a missing field raises."""
    report = json.loads(path.read_text(encoding="utf-8"))
    name = str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)
    machine = report.get("machine", {})
    source = (
        f"{name}: the val-256 benchmark (python -m bench.accuracy) of {report['date'][:10]} "
        f"on {machine.get('cpu', 'an unnamed CPU')}, {report.get('threads', '?')} threads, "
        f"commit {report.get('versions', {}).get('git_commit', 'unknown')[:12]}"
    )
    return BenchmarkFigures(_figures(report), name, source)


def measured_figures(
    spec: DecoderSpec, bench: BenchmarkFigures | None
) -> tuple[dict[str, Any], str]:
    """``spec``'s measured figures and where they come from: its model cards', else its
    rows in ``bench`` (:func:`benchmark_figures`); else ``{}`` and why, with where the
    figures are found."""
    if spec.figures:
        return spec.figures, spec.figures_source
    if bench is not None and spec.name in bench.by_decoder:
        return bench.by_decoder[spec.name], bench.source
    if bench is None:
        return {}, (
            "none measured in this installation: the val-256 figures of classical, refined "
            "and adaptive decoders are in bench/results/accuracy.json of a repository "
            "checkout (python -m bench.accuracy writes it; the service reads another copy "
            "named by MCAM_ACCURACY_REPORT) and in the README's 'Accuracy on val-256'"
        )
    return {}, (
        f"none measured: {bench.report} has no row for {spec.name}; "
        "python -m bench.accuracy measures every installed decoder"
    )
