"""The project's error types: one per stage, all :class:`NerfbakeError`, whose ``str`` is one line that names the
file and says what to do. The CLI prints that line and exits 2 (``--debug`` shows the traceback); anything else
reaching the CLI is a bug in nerfbake and is reported as one."""


class NerfbakeError(ValueError):
    """Bad input or a failed precondition a user can fix. (A ValueError, so callers catching that keep working.)"""


class RunFolderError(NerfbakeError):
    """A run folder (teacher, student, pipeline) that is missing, of another kind, or damaged."""


def reading(path, error: type[NerfbakeError], fix: str):
    """Context manager for a reader: any exception inside other than the project's own becomes ``error`` naming
    ``path``, what went wrong and ``fix`` -- a corrupt file must not surface as a zlib, tokenize or KeyError
    traceback. The readers still raise their own precise errors first; this catches what they did not foresee."""
    return _Reading(path, error, fix)


class _Reading:
    def __init__(self, path, error, fix):
        self.path, self.error, self.fix = path, error, fix

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if exc is None or isinstance(exc, (NerfbakeError, KeyboardInterrupt, SystemExit, GeneratorExit)):
            return False
        if not isinstance(exc, Exception):
            return False
        if isinstance(exc, FileNotFoundError):
            what = f"missing {exc.filename}" if exc.filename and str(exc.filename) != str(self.path) else "missing"
        elif isinstance(exc, MemoryError):
            what = "declares sizes too large to allocate (corrupt header?)"
        else:
            detail = " ".join(str(exc).split())[:200]
            what = f"unreadable ({type(exc).__name__}{': ' + detail if detail else ''})"
        raise self.error(f"{self.path}: {what}; {self.fix}") from exc
