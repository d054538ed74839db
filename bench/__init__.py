"""Benchmarks, run as ``python -m bench.NAME``; each prints a Markdown table and writes
``bench/results/NAME.json`` (plus a Markdown copy). Shared here: the facts every
report records (:func:`host_facts`: date, machine, package versions, load average) and
JSON writing (inf/NaN -> null).
Importing it keeps freed memory in the process, as ``mcam`` does
(:func:`models.allocator.keep_freed_memory`), so the benchmarks time what the service runs.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Callable, Collection, Iterable, Sequence
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import ModuleType
from typing import Any, NoReturn, get_args

from models.allocator import keep_freed_memory
from models.decoders import available_decoders
from models.decoders.registry import get_decoder, name_patterns, resolve
from models.errors import InvalidInputError, McamError
from models.formation import Encoding, SensorParams
from models.scenes import VAL256_CROPS_PER_SCENE, VAL_SCENES

keep_freed_memory()
RESULTS = Path(__file__).resolve().parent / "results"
#: A benchmark's ``main(argv)``: its exit code.
Main = Callable[[list[str] | None], int]
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


def host_facts() -> dict[str, Any]:
    """What every report records of where and when it was measured: the date, the
    machine, the package versions and the load average (1, 5 and 15 min) when the
    measuring ended (other processes share the cores, and timings grow with their load).
    Taken once everything is measured."""
    return {
        "date": utc_now(),
        "machine": machine(),
        "versions": versions(),
        "load_average": os.getloadavg(),
    }


def host_line(report: dict[str, Any]) -> str:
    """The date and host of a report's :func:`host_facts`, as its Markdown header says
    them: ``<date>, <cpu> (<cores> cores); load average at the end [1, 5, 15 min]``."""
    load = [round(value, 2) for value in report["load_average"]]
    host = report["machine"]
    return (
        f"{report['date']}, {host['cpu']} ({host['cores']} cores); "
        f"load average at the end {load}"
    )


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
    replace_text(out, json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n")
    replace_text(out.with_suffix(".md"), markdown + "\n")


def replace_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically: to a temporary file next to it, then renamed
    over it, so a reader (``GET /v1/decoders`` reads accuracy.json) never sees it half
    written."""
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        partial.write_text(text)
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)


def bench_parser(module: str, doc: str | None) -> argparse.ArgumentParser:
    """The argument parser of benchmark ``module`` (its ``__name__``): its usage names
    the command that runs it (``python -m bench.NAME``; the script's file name, which
    argparse gave, fails to import ``bench``), and ``doc``'s first paragraph describes it."""
    return argparse.ArgumentParser(
        prog=f"python -m {module_name(module)}", description=first_paragraph(doc)
    )


def first_paragraph(doc: str | None) -> str:
    """A module docstring's first paragraph on one line: a benchmark's ``--help``
    description (its first line alone cut bench.losses' sentence in half)."""
    return " ".join((doc or "").split("\n\n")[0].split())


def report_path(text: str) -> Path:
    """An argparse ``type``: a file to write a report to, in a folder that exists and
    takes files, else the parser's usage error naming the path (a folder, a missing
    folder or one that takes no files failed only when the report was written, after
    the whole measurement, with a traceback)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(
            f"{text} is a folder; name a file in it, e.g. {path / 'report.json'}"
        )
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(
            f"folder {path.parent} does not exist; create it or choose another path"
        )
    try:
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".mcam-bench-"):
            pass
    except OSError as exc:
        raise argparse.ArgumentTypeError(
            f"cannot write in {path.parent} ({exc.strerror}); choose a folder you may write"
        ) from None
    return path


def json_report_path(text: str) -> Path:
    """An argparse ``type``: :func:`report_path` of a JSON report, whose Markdown copy
    goes beside it as .md. A report named .md is refused: its copy replaced it, after
    the whole measurement, and the JSON was lost."""
    path = report_path(text)
    if path.suffix.lower() == ".md":
        raise argparse.ArgumentTypeError(
            f"{text} names the report's Markdown copy, which is written beside the JSON "
            f"report as .md and would replace it; name the report {path.with_suffix('.json')}"
        )
    return path


def add_report_option(
    parser: argparse.ArgumentParser, default: str, flag: str = "--out"
) -> None:
    """``--out PATH`` (or ``flag``): where the JSON report goes, its Markdown copy beside
    it as .md; ``default``: the file's name in bench/results/."""
    parser.add_argument(
        flag,
        type=json_report_path,
        default=RESULTS / default,
        help=f"JSON report, its Markdown copy beside it as .md (default bench/results/{default})",
    )


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


#: Frames of the val-256 set (:func:`models.scenes.val256_frames`).
VAL256_FRAMES = len(VAL_SCENES) * VAL256_CROPS_PER_SCENE


def val256_count(text: str) -> int:
    """An argparse ``type``: how many val-256 frames to use, 1 to :data:`VAL256_FRAMES`,
    else the parser's usage error naming the value (more ran the whole set, and
    bench.losses' report gave the count asked as the frames measured)."""
    value = at_least(1)(text)
    if value > VAL256_FRAMES:
        raise argparse.ArgumentTypeError(
            f"val-256 has {VAL256_FRAMES} frames, got {value}; give 1 to {VAL256_FRAMES}"
        )
    return value


def add_val256_frames_option(parser: argparse.ArgumentParser) -> None:
    """``--frames N``: the first N val-256 frames (1 to :data:`VAL256_FRAMES`, default
    all), the same option in every benchmark that measures on val-256."""
    parser.add_argument(
        "--frames", type=val256_count, default=VAL256_FRAMES, help="first N val-256 frames"
    )


def above_zero(text: str) -> float:
    """An argparse ``type``: a finite number above 0 (a rate), else the parser's usage
    error naming the value."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def given_twice(values: Sequence[Any]) -> list[Any]:
    """The values ``values`` holds more than once, each once, in order."""
    return list(dict.fromkeys(v for i, v in enumerate(values) if v in values[:i]))


def refuse_given_twice(values: Sequence[Any]) -> None:
    """Raise an ``argparse.ArgumentTypeError`` naming the values given more than once: a
    benchmark measures each value given, so one given twice was measured twice and
    reported twice (bench.video's summary kept the second alone, bench.stream's report
    the last)."""
    twice = given_twice(values)
    if twice:
        raise argparse.ArgumentTypeError(
            f"{', '.join(map(str, twice))} given more than once; give each once"
        )


class Distinct(argparse.Action):
    """The ``action`` of a list option (``nargs``): its values, refused with the
    parser's usage error when one is given twice (:func:`refuse_given_twice`)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        try:
            refuse_given_twice(values)
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentError(self, str(exc)) from None
        setattr(namespace, self.dest, values)


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
    encodings: Collection[str] = (),
) -> None:
    """Stop with the parser's usage error when any of ``names`` is neither a decoder the
    registry resolves (installed or parametrized, e.g. ``<net>+puma2``) nor one of the
    benchmark's own ``extra`` names, listing what it accepts; or when a decoder cannot
    decode one of the ``encodings`` the benchmark will give it (a net trained on one
    encoding, e.g. ``mantissanet-base-noise`` on modulo frames), naming what it decodes."""
    chosen = list(dict.fromkeys(names or ()))
    refuse_empty_names(parser, "decoders", chosen)
    unknown = sorted({name for name in chosen if name not in extra and not _resolves(name)})
    if unknown:
        accepted = [spec.name for spec in available_decoders()] + list(extra) + name_patterns()
        refuse_names(parser, "decoders", unknown, accepted)
    lacking = [
        f"{name} decodes {'/'.join(decodes)}, not {'/'.join(sorted(set(encodings) - set(decodes)))}"
        for name in chosen
        if name not in extra and not set(encodings) <= set(decodes := decoded_encodings(name))
    ]
    if lacking:
        parser.error(f"{'; '.join(lacking)}: choose other decoders or encodings")


def decoded_encodings(name: str) -> list[str]:
    """The encodings decoder ``name`` can unwrap (a learned one: those it has a model
    for; every decoder decodes ``clip`` frames, which never wrap, but a net unwraps
    none)."""
    decoder = get_decoder(name)
    return [
        encoding
        for encoding in get_args(Encoding)
        if decoder.unwraps(SensorParams(encoding=encoding))
    ]


def refuse_unknown(
    parser: argparse.ArgumentParser, what: str, names: Iterable[str], choices: Collection[str]
) -> None:
    """Stop with the parser's usage error when any of ``names`` is not in ``choices``
    (``what``: the option's plural noun, e.g. ``clips``), listing them."""
    names = list(names)
    refuse_empty_names(parser, what, names)
    unknown = sorted(set(names) - set(choices))
    if unknown:
        refuse_names(parser, what, unknown, choices)


def refuse_names(
    parser: argparse.ArgumentParser, what: str, unknown: list[str], accepted: Iterable[str]
) -> NoReturn:
    """Stop with the parser's usage error naming the ``unknown`` names and the
    ``accepted`` ones (``what``: the option's plural noun). A name with a comma is a list
    given the way bench.video takes it, to an option whose names are apart: that is
    said (``itoh,herraez`` was told only to choose from a list holding itoh and
    herraez)."""
    commas = (
        " (give the names apart, separated by spaces, not commas)"
        if any("," in name for name in unknown)
        else ""
    )
    parser.error(
        f"unknown {what} {', '.join(unknown)}{commas}; choose from: {', '.join(accepted)}"
    )


def refuse_empty_names(parser: argparse.ArgumentParser, what: str, names: list[str]) -> None:
    """Stop with the parser's usage error when one of ``names`` is empty or blank
    (``--decoders ''``, an unset shell variable): it was refused as "unknown decoders ;
    choose from ...", which named nothing (``what``: the option's plural noun)."""
    if any(not name.strip() for name in names):
        parser.error(
            f"an empty name among the {what} given ({', '.join(map(repr, names))}); name "
            "each one, or leave the option out for its default"
        )


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
) -> Main:
    """A benchmark's ``main(argv)``: parse (the arguments carry ``out``), run, publish
    (``rows``: the report's key of its measurements, which must not be empty); a
    :class:`models.errors.McamError` ends it as :func:`one_line_errors` says."""

    def main(argv: list[str] | None = None) -> int:
        args = parse_args(argv)
        report = run(args)
        return publish(report, markdown(report), args.out, rows=rows)

    main.__module__ = run.__module__
    return one_line_errors(main)


#: The optional dependencies (pyproject's extras) the benchmarks use, by extra.
EXTRAS = {"bench": ("matplotlib", "onnx", "httpx"), "train": ("torch", "onnx")}


def import_extra(module: str, extra: str, needed_by: str) -> ModuleType:
    """``module``, an optional dependency of the ``extra`` extra, imported; when it is
    not installed, :func:`missing_extra` ends the benchmark in one line."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing_extra(exc, extra, needed_by)


def missing_extra(exc: ModuleNotFoundError, extra: str, needed_by: str) -> NoReturn:
    """End with one line on stderr and exit code 2, as a usage error does: ``needed_by``
    (a benchmark, or one of its options) needs the module ``exc`` did not find, and the
    ``extra`` extra installs it (a traceback came at import, or after measuring). An
    error about any other module is raised again."""
    if (exc.name or "").split(".")[0] not in EXTRAS[extra]:
        raise exc
    sys.stderr.write(
        f"{needed_by}: error: it needs {exc.name}, which is not installed; install the "
        f"'{extra}' extra: pip install -c constraints.txt -e '.[{extra}]'\n"
    )
    raise SystemExit(2)


def one_line_errors(main: Main) -> Main:
    """``main`` that ends on a :class:`models.errors.McamError` (a mistake in what it
    was asked to measure, found while measuring) with the error's message on one line of
    stderr and exit code 2, as argparse ends a usage error, instead of a traceback."""

    @functools.wraps(main)
    def guarded(argv: list[str] | None = None) -> int:
        try:
            return main(argv)
        except McamError as exc:
            sys.stderr.write(f"{module_name(main.__module__)}: error: {exc.message}\n")
            raise SystemExit(2) from None

    return guarded


def module_name(module: str) -> str:
    """The dotted name of ``module``, also when it runs as ``__main__`` (``python -m``)."""
    spec = getattr(sys.modules.get(module), "__spec__", None)
    return spec.name if spec is not None else module
