"""The token never reaches a log line: one filter on every logger and handler the server has.

The page and the viewer pass the token in the query string once, WebSocket clients pass it on
every connection, and a log is read by more people than the token is for. uvicorn writes the
request target into its access lines (``uvicorn.access``) and into its WebSocket lines
(``uvicorn.error``), percent-encoded as the client sent it, so the filter blanks:

* the value after ``token=`` in any case and any key that ends in it (``?token=``,
  ``voxfusion_token=``), also spelled ``token%3D`` or ``token%253D``;
* the value after ``Bearer`` (an ``Authorization`` header, should anything log one);
* the configured token itself wherever it appears, each character as itself or
  percent-encoded (once or twice, hex in either case), ``+`` or ``%20`` for a space.

A filter on a logger sees only the records made on that logger, not those of its children;
a filter on a handler sees every record it writes. :func:`redact_logs` therefore puts the one
filter on the server's loggers, on every handler any logger has when it is called, and on
logging's last-resort handler.
"""

from __future__ import annotations

import logging
import re
import threading

REDACTED = "***"

_QUERY_VALUE = re.compile(r"(?i)(token(?:=|%3D|%253D))(?:%(?!26)[0-9a-f]{2}|[^&\s\"'%;,])*")
"""``token=`` (or its encodings) and its value, up to ``&``, ``%26``, a quote or a space."""
_BEARER_VALUE = re.compile(r"(?i)(bearer(?:\s|%20|\+)+)[^\s\"',;]+")

SERVER_LOGGERS = ("", "uvicorn", "uvicorn.error", "uvicorn.access", "fastapi", "server")
"""Loggers the filter is put on by name ("" is the root logger)."""


def secret_pattern(secret: str) -> re.Pattern:
    """A pattern for ``secret`` as written or percent-encoded, character by character (a
    client may encode any of them), in either case."""
    parts = []
    for character in secret:
        encoded = "".join(f"%(?:25)?{byte:02X}" for byte in character.encode())
        spellings = [re.escape(character), encoded] + (["\\+", "%(?:25)?20"] if character == " " else [])
        parts.append("(?:" + "|".join(spellings) + ")")
    return re.compile("".join(parts), re.IGNORECASE)


class RedactTokens(logging.Filter):
    """Blanks tokens in a record's message, arguments, traceback and stack (module doc)."""

    def __init__(self) -> None:
        super().__init__()
        self._secrets: tuple[re.Pattern, ...] = ()
        self._lock = threading.Lock()

    def add_secret(self, secret: str) -> None:
        """Blank ``secret`` from now on too (every app in this process adds its own token)."""
        if not secret:
            return
        with self._lock:
            patterns = {p.pattern: p for p in self._secrets}
            pattern = secret_pattern(secret)
            patterns.setdefault(pattern.pattern, pattern)
            # Longest first: a token that contains another is blanked whole.
            self._secrets = tuple(sorted(patterns.values(), key=lambda p: len(p.pattern), reverse=True))

    def redact(self, text: str) -> str:
        text = _QUERY_VALUE.sub(rf"\1{REDACTED}", text)
        text = _BEARER_VALUE.sub(rf"\1{REDACTED}", text)
        for pattern in self._secrets:
            text = pattern.sub(REDACTED, text)
        return text

    def _argument(self, value: object) -> object:
        if isinstance(value, str):
            return self.redact(value)
        if isinstance(value, (int, float, bool)) or value is None:
            return value  # kept as they are: a %d or %.1f format needs a number
        text = str(value)
        redacted = self.redact(text)
        return value if redacted == text else redacted

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = self.redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(self._argument(a) for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: self._argument(v) for k, v in record.args.items()}
        if record.exc_info and not record.exc_text:
            # Formatted here, once: every formatter prints exc_text when it is set.
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = self.redact(record.exc_text)
        if record.stack_info:
            record.stack_info = self.redact(record.stack_info)
        return True


_FILTER = RedactTokens()
"""The one filter of this process: installing it twice is a no-op, secrets accumulate."""


def _add_once(target: logging.Filterer) -> None:
    if _FILTER not in target.filters:
        target.addFilter(_FILTER)


def redact_logs(secret: str | None) -> RedactTokens:
    """Put the filter on the server's loggers and on every handler there is now (call it
    once logging is configured: uvicorn configures it before the app starts), blanking
    ``secret`` too when given. Returns the filter."""
    if secret:
        _FILTER.add_secret(secret)
    loggers = [logging.getLogger(name) for name in SERVER_LOGGERS]
    loggers += [item for item in list(logging.root.manager.loggerDict.values()) if isinstance(item, logging.Logger)]
    for logger in loggers:
        for handler in logger.handlers:
            _add_once(handler)
    for logger in loggers[:len(SERVER_LOGGERS)]:
        _add_once(logger)
    if logging.lastResort is not None:
        _add_once(logging.lastResort)
    return _FILTER
