"""Benchmarks, run as ``python -m bench.NAME``; each prints a Markdown table and writes
``bench/results/NAME.json`` (plus a Markdown copy). Shared here: the facts every
report records (date, machine, package versions) and JSON writing (inf/NaN -> null).
Importing it keeps freed memory in the process, as ``mcam`` does
(:func:`models.allocator.keep_freed_memory`), so the benchmarks time what the service runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
from collections.abc import Callable, Collection, Iterable
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from models.allocator import keep_freed_memory
from models.decoders import available_decoders
from models.decoders.registry import name_patterns, resolve
from models.errors import InvalidInputError
from models.formation import SensorParams

keep_freed_memory()
RESULTS = Path(__file__).resolve().parent / "results"
#: Distributions whose versions a report records.
PACKAGES = ("numpy", "scipy", "scikit-image", "onnxruntime", "PyMaxflow")


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux), else what platform knows."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """CPU model, logical cores, OS and Python of the machine running the benchmark."""
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "os": platform.platform(),
        "python": platform.python_version(),
    }


def versions() -> dict[str, str | None]:
    """Installed versions of the numeric packages and the git commit of the code."""
    found: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    found["git_commit"] = git_commit()
    return found


def git_commit() -> str | None:
    """HEAD of the repository holding this package, or None outside a git checkout."""
    try:
        done = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return None
    return done.stdout.strip()


def utc_now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no inf or NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    return value


def publish(report: dict[str, Any], markdown: str, out: Path, *, rows: str) -> int:
    """Write the report (JSON + Markdown, see :func:`write_report`), print the Markdown
    table; exit code 0."""
    write_report(report, markdown, out, rows=rows)
    print(markdown)
    return 0


def write_report(report: dict[str, Any], markdown: str, out: Path, *, rows: str) -> None:
    """Write ``report`` as JSON to ``out`` and ``markdown`` next to it (``.md``). A report
    whose ``rows`` (the key of its measurements) is empty is refused and nothing is
    written: it would replace the results at ``out`` with a report of nothing."""
    if not report[rows]:
        raise InvalidInputError(
            f"nothing was measured (the report's {rows!r} is empty), so {out} and its .md "
            "are left as they were; name at least one decoder or model to measure"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n")
    out.with_suffix(".md").write_text(markdown + "\n")


def at_least(minimum: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer of at least ``minimum``, else the parser's usage
    error naming the value (a count of 0 gave NaN timings or an IndexError after minutes
    of measuring)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


def read_noise(text: str) -> float:
    """An argparse ``type``: a read noise sigma in wraps, finite and in [0, 1] (what
    :class:`models.formation.SensorParams` takes), refused before anything is measured."""
    try:
        return SensorParams.parse({"read_noise": text}).read_noise
    except InvalidInputError:
        raise argparse.ArgumentTypeError(f"a read noise is in [0, 1] wraps, got {text}") from None


def refuse_unknown_decoders(
    parser: argparse.ArgumentParser,
    names: Iterable[str] | None,
    extra: Collection[str] = (),
) -> None:
    """Stop with the parser's usage error when any of ``names`` is neither a decoder the
    registry resolves (installed or parametrized, e.g. ``<net>+puma2``) nor one of the
    benchmark's own ``extra`` names, listing what it accepts."""
    unknown = sorted({name for name in names or () if name not in extra and not _resolves(name)})
    if unknown:
        accepted = [spec.name for spec in available_decoders()] + list(extra) + name_patterns()
        parser.error(f"unknown decoders {', '.join(unknown)}; choose from: {', '.join(accepted)}")


def refuse_unknown(
    parser: argparse.ArgumentParser, what: str, names: Iterable[str], choices: Collection[str]
) -> None:
    """Stop with the parser's usage error when any of ``names`` is not in ``choices``
    (``what``: the option's plural noun, e.g. ``clips``), listing them."""
    unknown = sorted(set(names) - set(choices))
    if unknown:
        parser.error(f"unknown {what} {', '.join(unknown)}; choose from: {', '.join(choices)}")


def _resolves(name: str) -> bool:
    try:
        resolve(name)
    except InvalidInputError:
        return False
    return True


def entry_point(
    parse_args: Callable[[list[str] | None], Any],
    run: Callable[[Any], dict[str, Any]],
    markdown: Callable[[dict[str, Any]], str],
    *,
    rows: str,
) -> Callable[[list[str] | None], int]:
    """A benchmark's ``main(argv)``: parse (the arguments carry ``out``), run, publish
    (``rows``: the report's key of its measurements, which must not be empty)."""

    def main(argv: list[str] | None = None) -> int:
        args = parse_args(argv)
        report = run(args)
        return publish(report, markdown(report), args.out, rows=rows)

    return main
