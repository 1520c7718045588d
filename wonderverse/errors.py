"""User-facing errors: the CLI prints them as one line and exits with code 2."""

import reprlib

from wonderverse.text import redact_urls


class WonderError(Exception):
    """A problem the user can fix (bad input, bad config, unusable store); never a bug."""


class ConfigError(WonderError):
    """An invalid scene spec, preset or step parameter; `field`: the dotted path of the (first) setting at fault,
    when one is."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class StoreError(WonderError):
    """A scene store that cannot be created, opened or written."""


SHOWN_MAX_CHARS = 60


class _Short(reprlib.Repr):
    def repr_str(self, x: str, level: int) -> str:
        return super().repr_str(redact_urls(x), level)  # before it is cut: a cut URL is no longer one


_short = _Short()
_short.maxlevel, _short.maxdict, _short.maxlist, _short.maxtuple, _short.maxset = 2, 4, 4, 4, 4
_short.maxstring, _short.maxother, _short.maxlong = SHOWN_MAX_CHARS, SHOWN_MAX_CHARS, SHOWN_MAX_CHARS


def shown(value: object, max_chars: int = SHOWN_MAX_CHARS) -> str:
    """`value` as an error message quotes it: its repr, at most `max_chars` characters, however large or deeply
    nested the value is (never the whole repr of a huge input)."""
    try:
        text = _short.repr(value)
    except Exception:  # an object whose repr fails (or an int over Python's digit limit)
        text = f"<{type(value).__name__}>"
    return text if len(text) <= max_chars else text[: max_chars - 3] + "..."
