"""User-facing errors: the CLI prints them as one line and exits with code 2."""


class WonderError(Exception):
    """A problem the user can fix (bad input, bad config, unusable store); never a bug."""


class ConfigError(WonderError):
    """An invalid scene spec, preset or step parameter."""


class StoreError(WonderError):
    """A scene store that cannot be created, opened or written."""
