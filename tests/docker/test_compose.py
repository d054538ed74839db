"""docker/: the compose file and the Dockerfile agree with the settings module and the CLI.

No Docker engine runs here, so the files are checked as data: every ``MCAM_*``
variable is a real setting with a value it accepts, and every command exists.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.core.config import Settings

DOCKER = Path(__file__).resolve().parents[2] / "docker"
PREFIX = "MCAM_"


def compose() -> dict[str, Any]:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def mcam_environment() -> list[tuple[str, str, str]]:
    """(service, variable, value) for every MCAM_* variable the compose file sets."""
    found = []
    for name, service in compose()["services"].items():
        for variable, value in (service.get("environment") or {}).items():
            if variable.startswith(PREFIX):
                found.append((name, variable, str(value)))
    return found


def dockerfile_environment() -> dict[str, str]:
    text = (DOCKER / "Dockerfile").read_text()
    return dict(re.findall(r"\b(MCAM_[A-Z_]+)=(\S+)", text))


def test_every_mcam_variable_is_a_setting() -> None:
    variables = {v for _, v, _ in mcam_environment()} | set(dockerfile_environment())
    assert len(variables) >= 8
    unknown = {v for v in variables if v[len(PREFIX) :].lower() not in Settings.model_fields}
    assert unknown == set()


def operator_supplied(value: str) -> bool:
    """Whether a compose value is substituted from the operator's environment (``${...}``)."""
    return value.startswith("${")


@pytest.mark.parametrize(
    ("service", "variable", "value"),
    [entry for entry in mcam_environment() if not operator_supplied(entry[2])],
)
def test_each_value_is_accepted(service: str, variable: str, value: str) -> None:
    field = variable[len(PREFIX) :].lower()
    Settings.model_validate({"data_dir": "/data", field: value})


def test_only_the_api_keys_come_from_the_operator_and_compose_requires_them() -> None:
    """``${VAR:?message}``: compose refuses to start without the keys (``${VAR}`` or
    ``${VAR:-}`` would start the API with none)."""
    supplied = {(v, value) for _, v, value in mcam_environment() if operator_supplied(value)}
    assert {v for v, _ in supplied} == {"MCAM_API_KEYS"}
    for _, value in supplied:
        assert re.fullmatch(r"\$\{MCAM_API_KEYS:\?[^}]*MCAM_API_KEYS[^}]*\}", value), value


def test_services_and_persistence() -> None:
    data = compose()
    services = data["services"]
    assert {"redis", "api", "worker-1", "worker-2", "simulator", "device"} <= set(services)
    assert "--appendonly" in services["redis"]["command"]
    redis_flags = services["redis"]["command"]
    assert redis_flags[redis_flags.index("--maxmemory-policy") + 1] == "noeviction"
    assert any(v.startswith("redis-data:") for v in services["redis"]["volumes"])
    for name in ("api", "worker-1", "worker-2"):
        assert services[name]["environment"]["MCAM_REDIS_URL"] == "redis://redis:6379/0"
        assert "mcam-data:/data" in services[name]["volumes"], name


def test_commands_parse_with_the_real_cli() -> None:
    from service.cli.main import build_parser

    parser = build_parser()
    commands = [
        service["command"][1:]
        for service in compose()["services"].values()
        if service.get("command", [""])[0] == "mcam"
    ]
    assert {argv[0] for argv in commands} == {"api", "worker", "simulate-device", "device"}
    for argv in commands:
        try:
            parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"compose runs 'mcam {' '.join(argv)}', which the CLI rejects")


def test_dockerfile_is_slim_non_root_with_health_check() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim", text, re.M)
    user = re.search(r"^USER (\S+)", text, re.M)
    assert user is not None and user.group(1) not in ("root", "0")
    assert "/health/live" in text and "HEALTHCHECK" in text
    assert 'CMD ["mcam", "serve"]' in text
    assert dockerfile_environment()["MCAM_DATA_DIR"] == "/data"


def test_an_init_reaps_and_forwards_signals_as_pid_1() -> None:
    """mcam serve as PID 1 would inherit, and never reap, the processes of a worker
    that died; tini does, and passes SIGTERM on."""
    text = (DOCKER / "Dockerfile").read_text()
    assert "install -y --no-install-recommends tini" in text
    assert 'ENTRYPOINT ["tini", "--"]' in text


def test_the_build_context_leaves_out_local_state() -> None:
    """The context is the repository: without .dockerignore it sent the virtualenv, the
    local service's data (its API keys, Redis files) and the git history."""
    ignored = (DOCKER.parent / ".dockerignore").read_text().split()
    assert {".git", ".venv", "data", "runs"} <= set(ignored)


def test_the_image_ships_the_benchmark_report_it_names() -> None:
    """GET /v1/decoders in the image gave classical and auto decoders no figures: their
    report lives in bench/results, which neither the image nor the build context had."""
    text = (DOCKER / "Dockerfile").read_text()
    named = dockerfile_environment()["MCAM_ACCURACY_REPORT"]
    workdir = re.search(r"^WORKDIR (\S+)", text, re.M)
    assert workdir is not None
    copies = dict(
        (str(Path(workdir.group(1)) / target), source)
        for source, target in re.findall(r"^COPY (\S+) (\S+)$", text, re.M)
    )
    assert named in copies
    assert (DOCKER.parent / copies[named]).is_file()
    ignored = (DOCKER.parent / ".dockerignore").read_text().split()
    assert f"!{copies[named]}" in ignored
