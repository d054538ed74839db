"""Tests of bench/__init__.py, the code the benchmarks share (no timings asserted)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import pytest

from bench import (
    add_report_option,
    bench_parser,
    colour,
    host_facts,
    refuse_unknown,
    refuse_unknown_decoders,
    write_report,
)
from models.errors import InvalidInputError


def test_a_report_of_nothing_is_refused_and_the_old_results_are_kept(tmp_path: Path) -> None:
    out = tmp_path / "profile.json"
    out.write_text('{"profiles": ["committed"]}\n')
    with pytest.raises(InvalidInputError, match="nothing was measured"):
        write_report({"date": "today", "profiles": []}, "empty", out, rows="profiles")
    assert out.read_text() == '{"profiles": ["committed"]}\n'
    assert not out.with_suffix(".md").exists()


def test_a_report_with_rows_is_written_as_json_and_markdown(tmp_path: Path) -> None:
    out = tmp_path / "sub" / "colour.json"
    write_report({"rows": [{"psnr": float("inf")}]}, "| table |", out, rows="rows")
    assert out.read_text() == '{\n  "rows": [\n    {\n      "psnr": null\n    }\n  ]\n}\n'
    assert out.with_suffix(".md").read_text() == "| table |\n"


def test_a_report_replaces_the_old_one_whole(tmp_path: Path) -> None:
    """The report was written in place, so a reader could read it half written; now a new
    file is renamed over it (a hard link to the old one keeps the old text)."""
    out = tmp_path / "accuracy.json"
    out.write_text('{"rows": ["old"]}\n')
    old = tmp_path / "old.json"
    old.hardlink_to(out)
    write_report({"rows": ["new"]}, "| new |", out, rows="rows")
    assert old.read_text() == '{"rows": ["old"]}\n'
    assert '"new"' in out.read_text()
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        "accuracy.json", "accuracy.md", "old.json"]


def test_a_mistake_found_while_measuring_ends_in_one_line_and_exit_code_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A McamError raised in a benchmark's run (here: the frames refused) was a traceback."""

    def refused(*_: object) -> None:
        raise InvalidInputError("no frames of that kind; choose another set")

    monkeypatch.setattr(colour, "frame_set", refused)
    with pytest.raises(SystemExit) as exc:
        colour.main(["--decoders", "itoh", "--out", str(tmp_path / "colour.json")])
    assert exc.value.code == 2
    assert capsys.readouterr().err == (
        "bench.colour: error: no frames of that kind; choose another set\n"
    )
    assert not (tmp_path / "colour.json").exists()


def test_host_facts_name_the_date_machine_versions_and_load() -> None:
    facts = host_facts()
    assert set(facts) == {"date", "machine", "versions", "load_average"}
    assert facts["machine"]["cores"] >= 1 and facts["versions"]["numpy"]
    assert len(facts["load_average"]) == 3


@pytest.mark.parametrize(
    ("refuse", "message"),
    [
        (lambda parser: refuse_unknown_decoders(parser, ["itoh", ""]),
         "an empty name among the decoders given ('itoh', ''); name each one, or leave the "
         "option out for its default"),
        (lambda parser: refuse_unknown_decoders(parser, [" "]),
         "an empty name among the decoders given (' ')"),
        (lambda parser: refuse_unknown(parser, "models", [""], ["mantissanet-tiny"]),
         "an empty name among the models given ('')"),
    ],
)  # fmt: skip
def test_an_empty_name_is_refused_as_empty(
    refuse: Callable[[argparse.ArgumentParser], None],
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An empty name (``--decoders ''``) was refused as "unknown decoders ; choose from:
    ...", naming nothing."""
    err = refusal(refuse, capsys)
    assert f"python -m bench.accuracy: error: {message}" in err
    assert "unknown" not in err


@pytest.mark.parametrize(
    ("refuse", "message"),
    [
        (lambda parser: refuse_unknown_decoders(parser, ["itoh,herraez"]),
         "unknown decoders itoh,herraez (give the names apart, separated by spaces, not "
         "commas); choose from: itoh, herraez"),
        (lambda parser: refuse_unknown(parser, "models", ["a,b"], ["a", "b"]),
         "unknown models a,b (give the names apart, separated by spaces, not commas); "
         "choose from: a, b"),
    ],
)  # fmt: skip
def test_a_comma_list_given_as_one_name_is_told_to_give_names_apart(
    refuse: Callable[[argparse.ArgumentParser], None],
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--decoders itoh,herraez`` (as bench.video takes it) was told only "unknown
    decoders itoh,herraez; choose from: itoh, herraez, ...", a list holding both."""
    assert f"python -m bench.accuracy: error: {message}" in refusal(refuse, capsys)


def refusal(
    refuse: Callable[[argparse.ArgumentParser], None], capsys: pytest.CaptureFixture[str]
) -> str:
    """The stderr of ``refuse`` given bench.accuracy's parser, which it must stop with
    exit code 2."""
    with pytest.raises(SystemExit) as exc:
        refuse(bench_parser("bench.accuracy", None))
    assert exc.value.code == 2
    return capsys.readouterr().err


def test_reports_default_outside_the_committed_results(reports_in_tmp: Path) -> None:
    """The tests' reports go to a temporary folder by default (tests/bench/conftest.py):
    a usage-error test whose refusal broke ran the benchmark without ``--out`` and
    overwrote bench/results/accuracy.json."""
    parser = argparse.ArgumentParser()
    add_report_option(parser, "accuracy.json")
    assert parser.parse_args([]).out == reports_in_tmp / "accuracy.json"
