"""Error messages as the API shows them: one readable ``{"detail": "..."}`` string.

FastAPI answers a request that fails validation with a list of pydantic error objects, while
every other error (and the API description) is ``{"detail": "what is wrong"}``; clients
should not need two parsers, so the list is joined into one sentence per field that keeps
the field's location (``body.intrinsics.fy: must be greater than 0``). Messages that name
files in the server's data folder are rewritten relative to the user's upload, so an error
never shows the disk layout or the id of a session that was never created.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

MAX_LISTED_ERRORS = 8
"""Validation errors spelled out in one message; the rest are counted."""


def _location(loc: Sequence[object]) -> str:
    return ".".join(str(part) for part in loc) or "request"


def _where(error: dict) -> str:
    loc = tuple(error.get("loc", ()))
    # A JSON syntax error's location is ("body", character offset): say where in words.
    if error.get("type") == "json_invalid" and len(loc) == 2 and isinstance(loc[1], int):
        return f"{loc[0]} (character {loc[1]})"
    return _location(loc)


def _message(error: dict) -> str:
    if error.get("type") == "json_invalid":
        reason = (error.get("ctx") or {}).get("error")
        return "not valid JSON" + (f" ({reason})" if reason else "")
    if error.get("type") == "finite_number":  # NaN or Infinity: pydantic's text names no limit
        return "must be a finite number"
    text = str(error.get("msg", "invalid value"))
    # pydantic prefixes the text of a validator's ValueError; the field location says enough.
    for prefix in ("Value error, ", "Assertion failed, "):
        text = text.removeprefix(prefix)
    return text


def validation_message(errors: Iterable[dict]) -> str:
    """pydantic/FastAPI error dicts -> ``"loc: msg; loc: msg"`` (at most MAX_LISTED_ERRORS)."""
    errors = list(errors)
    parts = [f"{_where(e)}: {_message(e)}" for e in errors[:MAX_LISTED_ERRORS]]
    if len(errors) > MAX_LISTED_ERRORS:
        parts.append(f"and {len(errors) - MAX_LISTED_ERRORS} more")
    return "; ".join(parts) or "the request is not valid"


def error_text(error: BaseException) -> str:
    """The message of an exception without the quotes ``str(KeyError(...))`` adds."""
    if isinstance(error, KeyError) and error.args:
        return str(error.args[0])
    return str(error)


def strip_paths(message: str, root: Path, replacement: str = "") -> str:
    """``message`` with ``root`` (as given and resolved) removed from file names under it, and
    ``root`` itself replaced by ``replacement``; longest spelling first."""
    spellings = sorted({str(root), str(root.resolve())}, key=len, reverse=True)
    for spelling in spellings:
        message = message.replace(spelling + "/", "")
    for spelling in spellings:
        message = message.replace(spelling, replacement)
    return message
