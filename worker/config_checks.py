"""One way for the worker's settings dataclasses to refuse bad values."""

from __future__ import annotations

from models.errors import InvalidInputError


def refuse_invalid(what: str, checks: dict[str, bool]) -> None:
    """Raise :class:`InvalidInputError` naming every failed check (text -> passed)."""
    problems = [text for text, ok in checks.items() if not ok]
    if problems:
        raise InvalidInputError(f"invalid {what} settings: {'; '.join(problems)}")


def heartbeat_problem(heartbeat_s: float, lease_ms: int, claim_idle_ms: int) -> str | None:
    """Why a worker beating every ``heartbeat_s`` (s) could not keep its device leases
    (``lease_ms``) and in-flight jobs (reclaimed after ``claim_idle_ms``) alive, or None."""
    if heartbeat_s * 1000 < min(lease_ms, claim_idle_ms):
        return None
    return (
        f"the heartbeat ({heartbeat_s} s) renews device leases and in-flight jobs: it must "
        f"be shorter than the lease ({lease_ms} ms) and the claim idle time "
        f"({claim_idle_ms} ms); lower MCAM_HEARTBEAT_S or raise MCAM_DEVICE_LEASE_MS / "
        "MCAM_CLAIM_IDLE_MS"
    )
