"""One exception type for bad input: its message is one line naming what was wrong."""


class PwsError(ValueError):
    """Invalid input or a request that cannot be satisfied soundly.

    The command line prints ``str(err)`` and exits with status 2; nodes log it and keep running.
    """


def require(condition: bool, message: str) -> None:
    """Raise :class:`PwsError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise PwsError(message)
