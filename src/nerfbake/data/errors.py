"""The one error type for bad input: its message names the file and says what to do."""


class DatasetError(ValueError):
    """A dataset file is missing, unreadable or inconsistent. ``str(err)`` is a one-line user-facing message."""
