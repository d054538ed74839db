"""Tests of service/core/config.py: MCAM_* settings from the environment and .env."""

from __future__ import annotations

import errno
import logging
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import ValidationError

from models.errors import InvalidInputError
from service.core.config import EMPTY_REDIS_BYTES, Settings, get_settings, upload_room


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """No MCAM_* variable of the caller leaks in; .env is looked for in an empty folder."""
    for name in [n for n in os.environ if n.startswith("MCAM_")]:
        monkeypatch.delenv(name)
    monkeypatch.chdir(tmp_path)


@pytest.fixture
def fresh_settings() -> Iterator[None]:
    """:func:`get_settings` reads the environment anew, and forgets what it read after."""
    get_settings.cache_clear()
    yield
    get_settings.cache_clear()


def test_defaults_are_the_embedded_local_service() -> None:
    settings = Settings()
    assert settings.data_dir == Path("data") and settings.redis_url is None
    assert (settings.host, settings.port) == ("127.0.0.1", 8000)
    assert settings.default_decoder == "auto" and settings.rate_limit_per_minute == 600


def test_environment_and_dotenv_override_with_the_prefix(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    (tmp_path / ".env").write_text("MCAM_PORT=9001\nMCAM_WORKER_THREADS=4\nOTHER=1\n")
    monkeypatch.setenv("MCAM_PORT", "9002")  # the environment wins over .env
    monkeypatch.setenv("MCAM_REDIS_URL", "redis://cache:6379/0")
    settings = Settings()
    assert settings.port == 9002 and settings.worker_threads == 4
    assert settings.redis_url == "redis://cache:6379/0"


def test_an_empty_variable_is_unset(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """MCAM_DATA_DIR= put the data (API keys, Redis files) in the working folder, and
    MCAM_PORT= or MCAM_ACCURACY_REPORT= stopped the service; each now means the default."""
    defaults = Settings()
    for name in Settings.model_fields:
        monkeypatch.setenv(f"MCAM_{name.upper()}", "")
    assert Settings() == defaults
    for name in Settings.model_fields:
        monkeypatch.delenv(f"MCAM_{name.upper()}")
    (tmp_path / ".env").write_text("MCAM_DATA_DIR=\nMCAM_PORT=\n")
    assert Settings() == defaults


def test_a_path_in_a_home_folder_is_read_as_a_shell_reads_it(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """MCAM_DATA_DIR=~/data in .env (no shell to expand it) put the data in a folder named
    '~' of the working folder, while mcam serve said the key was stored in ~/data."""
    home = tmp_path / "home"
    (home / "bench").mkdir(parents=True)
    shutil.copy(Path(__file__).parents[3] / "bench" / "results" / "accuracy.json", home / "bench")
    monkeypatch.setenv("HOME", str(home))
    (tmp_path / ".env").write_text(
        "MCAM_DATA_DIR=~/data\nMCAM_ACCURACY_REPORT=~/bench/accuracy.json\n"
    )
    settings = Settings()
    assert settings.data_dir == home / "data"
    assert settings.accuracy_report == home / "bench" / "accuracy.json"


@pytest.mark.usefixtures("fresh_settings")
def test_mcam_serve_giving_its_workers_the_home_data_dir_is_not_warned_of(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """mcam serve gives its workers the data dir's absolute path: with ~/data in .env each
    worker warned that MCAM_DATA_DIR was set both there and in the environment."""
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    (tmp_path / ".env").write_text("MCAM_DATA_DIR=~/data\n")
    monkeypatch.setenv("MCAM_DATA_DIR", str(tmp_path / "home" / "data"))
    with caplog.at_level(logging.WARNING, logger="service.core.config"):
        assert get_settings().data_dir == tmp_path / "home" / "data"
    assert not caplog.records


@pytest.mark.parametrize("host", [" 127.0.0.1", "127.0.0.1 ", "\t127.0.0.1\n"])
def test_spaces_around_the_host_are_dropped(monkeypatch: pytest.MonkeyPatch, host: str) -> None:
    """MCAM_HOST="127.0.0.1 " stopped the service with "cannot listen on 127.0.0.1 :8000
    (Name or service not known)": an address that looked right, the space unseen."""
    monkeypatch.setenv("MCAM_HOST", host)
    assert Settings().host == "127.0.0.1"


def test_the_home_of_no_user_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MCAM_DATA_DIR", "~no-such-user-of-mcam/data")
    with pytest.raises(ValidationError, match="the home of no user of this machine"):
        Settings()


@pytest.mark.parametrize(
    ("name", "value"),
    [("MCAM_PORT", "70000"), ("MCAM_WORKER_THREADS", "0"), ("MCAM_HEARTBEAT_S", "-1"),
     ("MCAM_RATE_LIMIT_PER_MINUTE", "many")],
)
def test_unreadable_values_name_their_setting(
    monkeypatch: pytest.MonkeyPatch, name: str, value: str
) -> None:
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError) as caught:
        Settings()
    assert caught.value.errors()[0]["loc"] == (name.removeprefix("MCAM_").lower(),)


@pytest.mark.parametrize("name", ["auto-40ms", "herraez+colour", "mantissanet-small+puma"])
def test_a_parametrized_default_decoder_is_accepted(
    monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    monkeypatch.setenv("MCAM_DEFAULT_DECODER", name)
    assert Settings().default_decoder == name


def test_an_unknown_default_decoder_stops_the_service_at_start(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """It started, then answered every request naming no decoder with 422 'unknown
    decoder', blaming the client for the operator's setting."""
    monkeypatch.setenv("MCAM_DEFAULT_DECODER", "nope")
    with pytest.raises(ValidationError, match="unknown decoder 'nope'; choose one of"):
        Settings()


def test_the_embedded_redis_must_have_room_beyond_the_queues_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Else Redis fills (503 store_full, workers stalled) before the queue's own bound
    answers 503 queue_full."""
    monkeypatch.setenv("MCAM_JOBS_MAX_BYTES", "1000")
    monkeypatch.setenv("MCAM_REDIS_MAXMEMORY", "4000000")
    assert Settings().redis_maxmemory == 4_000_000
    monkeypatch.setenv("MCAM_JOBS_MAX_BYTES", "4000000")
    with pytest.raises(ValidationError, match=r"must exceed MCAM_JOBS_MAX_BYTES \(4000000\)"):
        Settings()
    monkeypatch.setenv("MCAM_REDIS_URL", "redis://queue:6379/0")  # its own maxmemory
    assert Settings().redis_maxmemory == 4_000_000


def test_the_embedded_redis_must_have_room_for_the_largest_upload(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Redis holds an upload's codes twice while it takes them: with MCAM_JOBS_MAX_BYTES
    200 MB and MCAM_REDIS_MAXMEMORY 250 MB the service started, /health/ready never
    passed on an empty queue and a 64 M-sample video got 503 store_full, retried for
    good. It is refused at start; a smaller largest upload is taken."""
    monkeypatch.setenv("MCAM_JOBS_MAX_BYTES", "200000000")
    monkeypatch.setenv("MCAM_REDIS_MAXMEMORY", "250000000")
    with pytest.raises(ValidationError, match=r"MCAM_REDIS_MAXMEMORY \(250000000\) is below "
                       r"the 271646720 bytes the embedded Redis needs"):
        Settings()
    monkeypatch.setenv("MCAM_MAX_VIDEO_SAMPLES", "50000000")
    settings = Settings()
    assert settings.redis_maxmemory >= upload_room(settings) + EMPTY_REDIS_BYTES
    monkeypatch.delenv("MCAM_MAX_VIDEO_SAMPLES")
    monkeypatch.setenv("MCAM_REDIS_URL", "redis://queue:6379/0")  # its own maxmemory
    assert Settings().redis_maxmemory == 250_000_000


@pytest.mark.parametrize(
    "setting", [("MCAM_CLAIM_IDLE_MS", "1000"), ("MCAM_DEVICE_LEASE_MS", "2000")]
)
def test_a_heartbeat_too_slow_for_the_leases_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch, setting: tuple[str, str]
) -> None:
    """``mcam serve`` and ``mcam api`` read these settings too: they used to accept jobs
    for workers that exited at start, restarted over and over."""
    monkeypatch.setenv(*setting)
    with pytest.raises(ValidationError, match="must be shorter than the lease"):
        Settings()
    monkeypatch.setenv("MCAM_HEARTBEAT_S", "0.5")
    assert Settings().heartbeat_s == 0.5


@pytest.mark.parametrize("value", ["nan", "-nan", "inf", "-inf", "infinity"])
@pytest.mark.parametrize("name", ["MCAM_DECODE_WAIT_S", "MCAM_HEARTBEAT_S"])
def test_a_time_that_is_no_finite_number_is_refused_as_such(
    monkeypatch: pytest.MonkeyPatch, name: str, value: str
) -> None:
    """MCAM_DECODE_WAIT_S=nan was told "Input should be less than or equal to 300", and
    MCAM_HEARTBEAT_S=nan "greater than or equal to 0.1": bounds a nan neither passes nor
    fails, which said nothing of what was wrong."""
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError) as caught:
        Settings()
    [error] = caught.value.errors()
    assert error["loc"] == (name.removeprefix("MCAM_").lower(),)
    assert error["msg"] == "Input should be a finite number"


@pytest.mark.parametrize("value", ["inf", "1e20"])
def test_a_retention_redis_cannot_expire_by_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    """MCAM_RESULT_RETENTION_S=inf was accepted, and no decoded job could then be marked
    finished (its record's expiry: int(inf) raised OverflowError, and Redis refuses
    1e20 s): the worker handed it back, delivery after delivery. 100 years is the
    longest accepted."""
    monkeypatch.setenv("MCAM_RESULT_RETENTION_S", value)
    with pytest.raises(ValidationError) as caught:
        Settings()
    assert caught.value.errors()[0]["loc"] == ("result_retention_s",)
    monkeypatch.setenv("MCAM_RESULT_RETENTION_S", str(100 * 365.25 * 24 * 3600))
    assert Settings().result_retention_s == 100 * 365.25 * 24 * 3600


def test_more_worker_threads_than_a_session_can_use_are_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MCAM_WORKER_THREADS", "100000")
    with pytest.raises(ValidationError, match="less than or equal to 256"):
        Settings()
    monkeypatch.setenv("MCAM_WORKER_THREADS", "256")
    assert Settings().worker_threads == 256


#: Values each setting once accepted that then failed, and the limit now accepted.
FAILED_LATER = [
    # Redis refused SET PX of 2^63 ms or more: no worker could take a device.
    ("device_lease_ms", str(10**19), str(24 * 3600 * 1000)),
    # Redis refused XPENDING IDLE of 2^63 ms or more: no job was ever read.
    ("claim_idle_ms", str(10**19), str(24 * 3600 * 1000)),
    # Redis refused XADD MAXLEN of 2^63 or more: every device frame was dropped.
    ("frames_maxlen", str(10**19), str(2**20)),
    # Each worker grew by job threads (each to start a decoding process) until memory
    # ran out.
    ("worker_concurrency", str(10**19), "256"),
    # Each worker stopped at start with a traceback (the decode pool's barrier).
    ("stream_processes", str(10**19), "256"),
    # Workers beat in a busy loop (800 fsynced Redis commands a second), and
    # /health/ready, counting beats younger than three heartbeats (3 ns), found none.
    ("heartbeat_s", "1e-9", "0.1"),
    # The API answered 503 to requests Redis served in time (8 of 200 reads of a job on
    # an idle host; 18 at 0.001).
    ("redis_timeout_s", "1e-9", "0.1"),
    # The API closed 4 in 10 connections of a local client before their head was read.
    ("http_header_timeout_s", "1e-9", "1"),
    # Every 4 MB upload from the same host got 408, the client told to send without pauses.
    ("http_body_timeout_s", "1e-9", "1"),
    # Every upload got 408, even one of a 64 x 64 frame from the same host.
    ("http_body_deadline_s", "1e-9", "1"),
    # A client asking 'Prefer: wait=1000000000' that gave up after 2 s held a server
    # thread and a waiting slot for good: 70 s later another's wait=3 got 202 at once.
    ("max_prefer_wait_s", "inf", "3600"),
    # A job failing for the worker was retried after pauses doubling from 0.05 s (51 s
    # before its 12th try, 155 days before its 30th), the worker deaf to SIGTERM meanwhile.
    ("max_deliveries", "1000", "10"),
    # One client's unfinished head (300 MB of header lines) grew the API by 350 MB in
    # 2.3 s, and the header timeout let it go on for 10 s.
    ("http_max_header_bytes", str(10**19), str(2**20)),
    # A 100 MB JSON body from no key at all took the API 300 MB before its 401.
    ("max_json_bytes", str(10**19), str(2**20)),
    # Each response of the API logged "Exception in ASGI application" with an
    # OverflowError traceback (asyncio cannot time a delay past a float's range).
    ("http_keep_alive_s", str(10**400), "3600"),
]


@pytest.mark.parametrize(("name", "refused", "accepted"), FAILED_LATER)
def test_a_value_that_failed_later_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch, name: str, refused: str, accepted: str
) -> None:
    """Each was accepted and failed once the service ran (see FAILED_LATER); each is now
    refused at start, naming its setting, and the limit itself is taken."""
    monkeypatch.setenv(f"MCAM_{name.upper()}", refused)
    with pytest.raises(ValidationError) as caught:
        Settings()
    assert caught.value.errors()[0]["loc"] == (name,)
    monkeypatch.setenv(f"MCAM_{name.upper()}", accepted)
    assert float(getattr(Settings(), name)) == float(accepted)


@pytest.mark.usefixtures("fresh_settings")
def test_a_misspelt_setting_is_refused_with_the_name_meant(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """MCAM_MAX_PIXEL (for MCAM_MAX_PIXELS) was ignored without a word: the service ran
    on the default the operator meant to change. It is now refused, in the environment
    or .env, naming the setting it resembles; other variables of .env are left alone."""
    monkeypatch.setenv("MCAM_MAX_PIXEL", "1000")
    with pytest.raises(InvalidInputError, match=r"MCAM_MAX_PIXEL \(environment\) is no "
                       r"setting: did you mean MCAM_MAX_PIXELS\?"):
        get_settings()
    monkeypatch.delenv("MCAM_MAX_PIXEL")
    (tmp_path / ".env").write_text("OTHER=1\nMCAM_PORT=9001\nmcam_heartbeat=1\n")
    with pytest.raises(InvalidInputError, match=r"mcam_heartbeat \(\.env\) is no setting: "
                       r"did you mean MCAM_HEARTBEAT_S\?"):
        get_settings()
    (tmp_path / ".env").write_text("OTHER=1\nMCAM_PORT=9001\n")
    assert get_settings().port == 9001


@pytest.mark.usefixtures("fresh_settings")
def test_a_line_of_dotenv_that_does_not_parse_is_refused(tmp_path: Path) -> None:
    """python-dotenv logged "could not parse statement starting at line 3" and dropped
    the line: the service ran without the setting in it (here an unclosed quote)."""
    (tmp_path / ".env").write_text('MCAM_PORT=9001\n# a comment\nMCAM_HOST="0.0.0.0\n')
    with pytest.raises(InvalidInputError, match=r"line 3 of \.env is not NAME=value"):
        get_settings()
    (tmp_path / ".env").write_text('MCAM_PORT=9001\n# a comment\nMCAM_HOST="0.0.0.0"\n')
    assert get_settings().host == "0.0.0.0"


@pytest.mark.usefixtures("fresh_settings")
def test_a_dotenv_that_is_not_utf8_is_refused(tmp_path: Path) -> None:
    """A .env saved as UTF-16 (a Windows editor's "Unicode") stopped every command with
    a UnicodeDecodeError traceback."""
    (tmp_path / ".env").write_text("MCAM_PORT=9001\n", encoding="utf-16")
    with pytest.raises(InvalidInputError, match=r"\.env is not utf-8 text \(byte 0 is 0xff\): "
                       "save it as utf-8"):
        get_settings()


def test_an_upload_limit_past_the_data_dirs_disk_is_refused(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """/health/ready wants room for one upload on the data dir's disk: with
    MCAM_MAX_UPLOAD_BYTES past the whole disk the service started and was never ready
    ("the result store's disk has ... bytes free, less than one upload")."""
    total = shutil.disk_usage(tmp_path).total
    monkeypatch.setenv("MCAM_DATA_DIR", str(tmp_path / "not" / "made" / "yet"))
    monkeypatch.setenv("MCAM_MAX_UPLOAD_BYTES", str(total + 1))
    with pytest.raises(ValidationError, match=r"is more than the whole disk of the data dir "
                       rf"holds \({tmp_path}: {total} bytes\)"):
        Settings()
    monkeypatch.setenv("MCAM_MAX_UPLOAD_BYTES", str(total))
    assert Settings().max_upload_bytes == total


@pytest.mark.parametrize(
    ("url", "problem"),
    [("foo", "unsupported Redis URL"),
     ("redis://:s3cret@localhost:notaport", "Port could not be cast to integer"),
     ("redis://localhost:99999", "Port out of range"),
     ("redis://:s3cret@[::1", "Invalid IPv6 URL")],
)
def test_a_redis_url_of_the_wrong_form_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch, url: str, problem: str
) -> None:
    """'foo' stopped mcam api and mcam serve after their start with an 89-line traceback
    (exit 3); a port that is no number, or an unclosed IPv6 bracket, stopped mcam worker
    with redis-py's ValueError traceback. Each is refused at start, its password masked."""
    monkeypatch.setenv("MCAM_REDIS_URL", url)
    with pytest.raises(ValidationError) as caught:
        Settings()
    message = caught.value.errors()[0]["msg"]
    assert problem in message and "s3cret" not in message
    assert "unset MCAM_REDIS_URL for the embedded Redis" in message


@pytest.mark.parametrize("url", ["redis://:s3cret@host:6379/abc", "rediss://host/1/2",
                                 "redis://host/-1"])
def test_a_redis_database_that_is_no_number_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch, url: str
) -> None:
    """redis-py took redis://host:6379/abc as database 0 without a word (and /1/2 as
    database 12): jobs went to another database than the operator named."""
    monkeypatch.setenv("MCAM_REDIS_URL", url)
    with pytest.raises(ValidationError) as caught:
        Settings()
    message = caught.value.errors()[0]["msg"]
    assert "database" in message and "is no whole number" in message
    assert "s3cret" not in message


@pytest.mark.parametrize("url", ["redis://host:6379/0", "redis://host/15/", "redis://host/",
                                 "redis://host", "unix:///run/redis.sock?db=3"])
def test_a_redis_url_with_a_database_number_or_none_is_taken(
    monkeypatch: pytest.MonkeyPatch, url: str
) -> None:
    monkeypatch.setenv("MCAM_REDIS_URL", url)
    assert Settings().redis_url == url


@pytest.mark.usefixtures("fresh_settings")
def test_a_setting_the_environment_overrides_in_dotenv_is_warned_of(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """MCAM_PORT=9001 in .env and 9002 in the environment: the service listened on 9002
    without a word on the line of .env it ignored. The same value twice, or an empty
    one in the environment (unset), is not warned of."""
    (tmp_path / ".env").write_text(
        "MCAM_PORT=9001\nMCAM_HOST=0.0.0.0\nMCAM_DATA_DIR=d\nTZ=UTC\n"
    )
    monkeypatch.setenv("TZ", "Europe/Paris")  # not a setting: not ours to judge
    monkeypatch.setenv("MCAM_PORT", "9002")
    monkeypatch.setenv("MCAM_HOST", "0.0.0.0")
    monkeypatch.setenv("MCAM_DATA_DIR", "")
    with caplog.at_level(logging.WARNING, logger="service.core.config"):
        settings = get_settings()
    assert (settings.port, settings.data_dir) == (9002, Path("d"))
    assert [record.getMessage() for record in caplog.records] == [
        "MCAM_PORT is set both in the environment and in .env, to other values: the "
        "environment's is used; remove one of them"
    ]
    caplog.clear()
    get_settings.cache_clear()
    # mcam serve gives its workers the data dir resolved: the same folder, no warning.
    monkeypatch.setenv("MCAM_DATA_DIR", str(tmp_path / "d"))
    monkeypatch.delenv("MCAM_PORT")
    with caplog.at_level(logging.WARNING, logger="service.core.config"):
        get_settings()
    assert not caplog.records


@pytest.mark.usefixtures("fresh_settings")
def test_a_dotenv_that_cannot_be_read_is_refused(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A folder named .env (what docker makes of a bind mount whose file is missing) was
    skipped without a word, the service run on defaults; one the user may not read
    was blamed as "permission denied: .env; choose a path you may read or write"."""
    (tmp_path / ".env").mkdir()
    with pytest.raises(InvalidInputError, match=r"cannot read \.env \(Is a directory\): make "
                       "it a file of NAME=value lines that the service's user may read"):
        get_settings()
    (tmp_path / ".env").rmdir()
    (tmp_path / ".env").write_text("MCAM_PORT=9001\n")

    def refuse(*_: object, **__: object) -> str:
        raise PermissionError(errno.EACCES, "Permission denied", ".env")

    monkeypatch.setattr(Path, "read_text", refuse)  # root reads any file
    with pytest.raises(InvalidInputError, match=r"cannot read \.env \(Permission denied\)"):
        get_settings()
