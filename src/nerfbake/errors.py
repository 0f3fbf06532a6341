"""The project's error types: one per stage, all :class:`NerfbakeError`, whose ``str`` is one line that names the
file and says what to do. The CLI prints that line and exits 2 (``--debug`` shows the traceback); anything else
reaching the CLI is a bug in nerfbake and is reported as one."""


class NerfbakeError(ValueError):
    """Bad input or a failed precondition a user can fix. (A ValueError, so callers catching that keep working.)"""


class RunFolderError(NerfbakeError):
    """A run folder (teacher, student, pipeline) that is missing, of another kind, or damaged."""
