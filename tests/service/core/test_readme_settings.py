"""The README's ``MCAM_*`` defaults against ``Settings.model_fields``: the one place the
documented numbers are checked, read from the README's text rather than from constants
imported from the code (which pass whatever the code says)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from service.core.config import Settings

README = Path(__file__).resolve().parents[3] / "README.md"
#: Multipliers of the units the README writes defaults in (bytes, seconds).
UNITS = {"KiB": 1024, "MiB": 1024**2, "GiB": 1024**3, "s": 1, "days": 24 * 3600}
#: ``(value`` or ``(value, ...``: a number, a power (``4096^2``), a unit after it.
NUMBER = re.compile(r"(\d+(?:\.\d+)?)(?:\^(\d+))?(?: (KiB|MiB|GiB|s|days)\b)?")
#: Settings whose default the README gives in words only, and why.
IN_WORDS = {
    "stream_processes": "one process per core, 'below'",
    "metrics_public": "off: '/metrics' needs a read key 'unless MCAM_METRICS_PUBLIC=true'",
    "ort_spin": "off: 'MCAM_ORT_SPIN=1 lets idle ONNX threads spin'",
}
#: What a mention of a setting says that is not a default ("see Cameras", "below").
NO_DEFAULT = object()


def readme_text() -> str:
    """The README with every run of whitespace (line breaks too) as one space."""
    return " ".join(README.read_text().split())


def documented_default(said: str) -> object:
    """The default a README mention states, from the text after the setting's name:
    ``unset: ...`` is None, a backquoted word or an address is text, a number is scaled
    by its unit; :data:`NO_DEFAULT` when it states none."""
    if re.search(r"(^|; )unset:", said):
        return None
    head = re.split(r"[,;:]", said, maxsplit=1)[0].strip()
    if word := re.fullmatch(r"`([^`]+)`", head):
        return word.group(1)
    if re.fullmatch(r"\d+(\.\d+){3}", head):
        return head
    number = NUMBER.match(head)
    if number is None:
        return NO_DEFAULT
    value = float(number.group(1)) ** int(number.group(2) or 1)
    return value * UNITS.get(number.group(3), 1)


def readme_defaults() -> list[tuple[str, object, str]]:
    """(setting, its documented default, the text) for each mention that states one:
    ``MCAM_X`` (default, ...) and ``MCAM_X``, default, ..."""
    text = readme_text()
    found = []
    mentions = re.finditer(r"`MCAM_([A-Z0-9_]+)` \(([^)]*)\)", text)
    listed = re.finditer(r"`MCAM_([A-Z0-9_]+)`, (\d[^,:;]*[,:;])", text)
    for mention in [*mentions, *listed]:
        default = documented_default(mention.group(2))
        if default is not NO_DEFAULT:
            found.append((mention.group(1).lower(), default, mention.group(2)[:60]))
    return found


def same_default(code: Any, documented: object) -> bool:
    """Whether the code's default is the documented one (numbers as numbers, paths and
    words as text)."""
    if documented is None or code is None:
        return code is documented
    if isinstance(documented, float):
        return not isinstance(code, bool) and isinstance(code, int | float) and code == documented
    return str(code) == documented


DEFAULTS = readme_defaults()


@pytest.mark.parametrize(("setting", "documented", "said"), DEFAULTS,
                         ids=[f"{s}: {d}" for s, d, _ in DEFAULTS])
def test_each_documented_default_is_the_settings_default(setting: str, documented: object,
                                                         said: str) -> None:
    assert setting in Settings.model_fields, f"the README documents MCAM_{setting.upper()}"
    code = Settings.model_fields[setting].default
    assert same_default(code, documented), (
        f"README: MCAM_{setting.upper()} ({said}...) gives {documented!r}; the code's "
        f"default is {code!r}: change one to match the other"
    )


def test_every_setting_is_documented_with_its_default() -> None:
    text = readme_text()
    named = {name.lower() for name in re.findall(r"`MCAM_([A-Z0-9_]+)", text)}
    assert set(Settings.model_fields) - named == set(), "settings the README never names"
    with_default = {setting for setting, _, _ in DEFAULTS}
    assert set(Settings.model_fields) - with_default == set(IN_WORDS)
