"""One exception type for bad input: its message is one line naming what was wrong."""


class PwsError(ValueError):
    """Invalid input or a request that cannot be satisfied soundly.

    The command line prints ``str(err)`` and exits with status 2; nodes log it and keep running.
    """


def require(condition: bool, message: str) -> None:
    """Raise :class:`PwsError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise PwsError(message)


def read_yaml_file(path, what: str = "file"):
    """The content of a YAML file; PwsError naming ``what`` and the path when it is missing or not valid YAML."""
    from pathlib import Path

    import yaml

    path = Path(path)
    require(path.is_file(), f"{what} not found: {path}")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise PwsError(f"{what} {path} is not valid YAML: {str(exc).splitlines()[0]}") from None


def require_creatable(path, what: str) -> None:
    """PwsError naming ``what`` unless ``path`` can be made (or, an existing folder, written in): the nearest
    existing folder at or above it is a folder (not a file) that this process may write in. Nothing is created
    (checked before a long run, so that its outputs are not lost at the end)."""
    import os
    from pathlib import Path

    p = Path(path).expanduser().absolute()
    above = p if p.is_dir() else p.parent   # (an existing folder: written in)
    while not above.exists() and above != above.parent:
        above = above.parent
    require(above.is_dir(), f"{what} {path}: {above} is a file, not a folder")
    require(os.access(above, os.W_OK | os.X_OK), f"{what} {path}: the folder {above} is not writable")
