"""Judging the user's words and names before anything heavy loads: control characters, invisible text, secrets in
URLs.

Standard library only, so that a command refuses a bad prompt, a bad name or a leaking URL in the time Python takes to
start (the CLI judges its arguments with these before it imports pydantic, numpy or zarr). The config's validators
use the same functions, so the messages are the same wherever the words come from.
"""

from __future__ import annotations

import re
import unicodedata

# Whitespace a user may type or paste into words (a tab, a line break): it becomes a single space, as any run of
# whitespace does. Every other control character (C0, DEL, C1: ESC and CSI start terminal escapes, BEL rings, BS
# and CR rewrite the line) is refused, so the words stored in a scene and echoed to a terminal are plain text.
ALLOWED_CONTROLS = frozenset("\t\n\r")
CONTROL_NAMES = {0x00: "NUL", 0x07: "BEL", 0x08: "BS", 0x0B: "VT", 0x0C: "FF", 0x1B: "ESC", 0x7F: "DEL", 0x9B: "CSI"}
# Bidirectional formatting characters: they reorder what a terminal or a browser shows (a name or a message can read
# as something else than what it is: "Trojan Source"), so words refuse them and error lines escape them as they
# escape C0 and C1.
BIDI_NAMES = {
    0x061C: "ALM",
    0x200E: "LRM",
    0x200F: "RLM",
    0x202A: "LRE",
    0x202B: "RLE",
    0x202C: "PDF",
    0x202D: "LRO",
    0x202E: "RLO",
    0x2066: "LRI",
    0x2067: "RLI",
    0x2068: "FSI",
    0x2069: "PDI",
}
# Letters that draw nothing (fillers, blank patterns): with format characters (zero-width space, joiners, BOM),
# combining marks alone and whitespace, text made only of these is invisible.
_BLANK_LETTERS = frozenset("\u115f\u1160\u3164\uffa0\u2800\u180e")
# user:password@ in a URL (scheme://user:password@host): the password part, what must never be shown or stored.
_URL_PASSWORD = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.-]*://[^\s/@:]*:)(?P<password>[^\s/@]*)@")
REDACTED = "***"
MAX_PROMPT_CHARS = 2000


def _is_control(c: str) -> bool:
    code = ord(c)
    return ((code < 0x20 or 0x7F <= code < 0xA0) and c not in ALLOWED_CONTROLS) or code in BIDI_NAMES


def control_character(text: str) -> str | None:
    """What is wrong with `text` for words stored and shown (a prompt, an extension, a name): the first control
    character other than a tab or a line break (C0, DEL, C1, or a bidirectional formatting character), named with its
    code point and position ('U+001B (ESC) at character 3'); None when there is none."""
    for i, c in enumerate(text):
        if _is_control(c):
            code = ord(c)
            short = CONTROL_NAMES.get(code) or BIDI_NAMES.get(code)
            name = f" ({short})" if short else ""
            return f"U+{code:04X}{name} at character {i + 1}"
    return None


def plain_words(text: str, what: str) -> str:
    """`text` with every run of whitespace (tabs and line breaks included) as one space; ValueError naming `what`
    when it holds any other control character (a terminal escape, a bell, a bidirectional override)."""
    bad = control_character(text)
    if bad is not None:
        raise ValueError(
            f"{what} holds the control character {bad}; control characters and terminal escapes are not allowed"
        )
    return " ".join(text.split())


def visible(text: str) -> bool:
    """Whether `text` shows anything: a character that is not whitespace, a format character (zero-width space,
    joiners, BOM, bidi marks), a combining mark on its own, or a blank filler letter."""
    for c in text:
        if c.isspace() or c in _BLANK_LETTERS:
            continue
        if unicodedata.category(c) in ("Cf", "Cc", "Cs", "Co", "Cn", "Mn", "Me", "Zs", "Zl", "Zp"):
            continue
        return True
    return False


def words_problem(text: str, what: str, max_chars: int) -> str | None:
    """What makes `text` unusable as `what` (the prompt, an extension request): a control character, no visible
    character, more than `max_chars` characters; None when usable. The config's validators and the CLI's early
    checks both use it."""
    try:
        words = plain_words(text, what)
    except ValueError as e:
        return str(e)
    if not words:
        return f"{what.removeprefix('the ')} is empty"
    if not visible(words):
        return f"{what.removeprefix('the ')} is empty: it holds no visible character (only invisible ones)"
    if len(words) > max_chars:
        return f"{what.removeprefix('the ')} has {len(words)} characters; at most {max_chars} are allowed"
    return None


def escaped(text: str) -> str:
    """`text` as one line for a terminal: every run of whitespace one space, and every control character (C0, C1,
    bidirectional formatting) written as its escape, never sent as it is."""
    text = " ".join(text.split())
    if control_character(text) is None:
        return text
    return "".join(c.encode("unicode_escape").decode() if _is_control(c) else c for c in text)


def error_line(message: str) -> str:
    """`message` as one line for a terminal: every run of whitespace one space, any other control character (a
    terminal escape or a bidirectional override in a file name or a setting's name) written as its escape, never
    sent as it is, and the password of any URL in it redacted (the CLI's `error:` lines, the studio's errors)."""
    return escaped(redact_urls(message))


def redact_urls(text: str) -> str:
    """`text` with the password of every `scheme://user:password@host` in it replaced by ***: what every message,
    log line and report shows of a URL that carries credentials."""
    return _URL_PASSWORD.sub(lambda m: f"{m['head']}{REDACTED}@", text)


def url_credentials(url: str) -> str | None:
    """Why `url` may not be stored (it carries a user name or a password: `http://user:secret@host/v1`), None when it
    carries none. The message quotes the URL with its password redacted."""
    _, sep, rest = url.partition("://")
    if not sep:
        return None
    authority = re.split(r"[/?#]", rest, maxsplit=1)[0]
    if "@" not in authority:
        return None
    return (
        f"the URL {redact_urls(url)!r} carries credentials (user:password@); they would be shown and stored with the "
        "scene: put the key in an environment variable and name it in api_key_env instead"
    )


# Names that become one folder (a batch spec's scene, a studio scene, a child of --out): how long one may be, in
# bytes of UTF-8 (the usual file-name limit).
MAX_NAME_BYTES = 255


def scene_name_problem(name: str) -> str | None:
    """Why `name` cannot name a scene folder inside a folder of scenes, None when it can: the one confinement rule for
    every name that becomes a path (batch spec names, studio scenes, children of --out). A name is a single path
    component that, after Unicode normalisation (NFKC: fullwidth dots and slashes are dots and slashes), is not empty,
    not '.' or '..', not hidden (a leading dot), holds no '/', '\\' or control character, shows something, has no
    space at either end, and fits in MAX_NAME_BYTES bytes."""
    if not isinstance(name, str):
        return f"a scene name is text, not {type(name).__name__}"
    norm = unicodedata.normalize("NFKC", name)
    bad = control_character(name) or control_character(norm)
    if bad is not None:
        return f"it holds the control character {bad}"
    if any(c in ALLOWED_CONTROLS for c in norm):
        return "it holds a tab or a line break"
    if not norm or not visible(norm):
        return "it is empty or shows nothing"
    if norm in (".", ".."):
        return f"{norm!r} is not a folder of its own"
    if any(sep in norm for sep in ("/", "\\", "\x00")) or any(sep in name for sep in ("/", "\\")):
        return "it holds a path separator ('/' or '\\'): a scene name is one folder name"
    if norm.startswith("."):
        return "it starts with a dot (a hidden name)"
    if norm != norm.strip() or name != name.strip():
        return "it starts or ends with a space"
    if len(name.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES:
        return f"it is longer than {MAX_NAME_BYTES} bytes"
    return None
