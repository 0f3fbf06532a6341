"""Bad dataset input: its message names the file and says what to do."""

from nerfbake.errors import NerfbakeError


class DatasetError(NerfbakeError):
    """A dataset file is missing, unreadable or inconsistent. ``str(err)`` is a one-line user-facing message."""
