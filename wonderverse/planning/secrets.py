"""Keeping an API key out of everything we write: reasons, errors, stored attributes and logs.

A server may echo the key (an Authorization header in an error page, the key in a "bad key" message), and the
text is later cut short for a one-line reason: a cut key is still a secret. So every run of 8 or more characters
of the key (the whole key, any prefix, any part) is masked, and this happens where the server's text first
enters our code, before anything shortens it.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

MIN_SECRET_RUN = 8  # shorter runs of a key's characters are too common in ordinary text to be a leak
MASK = "***"
# the libraries that log what a chat server says (httpx: the status line; httpcore: response headers at DEBUG)
HTTP_LOGGERS = ("httpx", *(f"httpcore.{n}" for n in ("connection", "http11", "http2", "proxy", "socks")))


def mask_secret(text: str, secret: str | None, mask: str = MASK) -> str:
    """`text` with every maximal run of characters that is a substring of `secret` and at least
    MIN_SECRET_RUN long replaced by `mask` (adjacent or overlapping runs become one mask). A secret shorter than
    that is masked where it occurs whole. No secret: `text` as it is."""
    if not secret or not text:
        return text
    if len(secret) < MIN_SECRET_RUN:
        return text.replace(secret, mask)
    # Every substring of the secret of length >= n is covered by the secret's n-grams that it contains, so the
    # union of the n-grams' occurrences is exactly what must go; str.find keeps the scan in C.
    spans: list[tuple[int, int]] = []
    for gram in {secret[i : i + MIN_SECRET_RUN] for i in range(len(secret) - MIN_SECRET_RUN + 1)}:
        at = text.find(gram)
        while at != -1:
            spans.append((at, at + MIN_SECRET_RUN))
            at = text.find(gram, at + 1)
    if not spans:
        return text
    spans.sort()
    out, kept_to = [], 0
    start, end = spans[0]
    for s, e in spans[1:]:
        if s > end:
            out += [text[kept_to:start], mask]
            kept_to, start = end, s
        end = max(end, e)
    out += [text[kept_to:start], mask, text[end:]]
    return "".join(out)


class _MaskingFilter(logging.Filter):
    def __init__(self, secret: str) -> None:
        super().__init__()
        self.secret = secret

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        masked = mask_secret(message, self.secret)
        if masked != message:
            record.msg, record.args = masked, None
        return True


@contextmanager
def masked_logs(secret: str | None, names: tuple[str, ...] = HTTP_LOGGERS) -> Iterator[None]:
    """While inside: records of the loggers `names` (where they are made, before any handler sees them) have
    `secret` masked as `mask_secret` does."""
    if not secret:
        yield
        return
    masking = _MaskingFilter(secret)
    loggers = [logging.getLogger(n) for n in names]
    for lg in loggers:
        lg.addFilter(masking)
    try:
        yield
    finally:
        for lg in loggers:
            lg.removeFilter(masking)
