"""The project's error types: one per stage, all :class:`NerfbakeError`, whose ``str`` is one line that names the
file and says what to do. The CLI prints that line and exits 2 (``--debug`` shows the traceback); anything else
reaching the CLI is a bug in nerfbake and is reported as one."""
from contextlib import contextmanager


class NerfbakeError(ValueError):
    """Bad input or a failed precondition a user can fix. (A ValueError, so callers catching that keep working.)"""


class RunFolderError(NerfbakeError):
    """A run folder (teacher, student, pipeline) that is missing, of another kind, or damaged."""


@contextmanager
def reading(path, error: type[NerfbakeError], fix: str):
    """Around a reader: any exception inside other than the project's own becomes ``error`` naming ``path``, what
    went wrong and ``fix`` -- a corrupt file must not surface as a zlib, tokenize or KeyError traceback. The readers
    still raise their own precise errors first; this catches what they did not foresee. (KeyboardInterrupt and
    SystemExit are not Exceptions and pass through.)"""
    try:
        yield
    except NerfbakeError:
        raise
    except FileNotFoundError as exc:
        what = f"missing {exc.filename}" if exc.filename and str(exc.filename) != str(path) else "missing"
        raise error(f"{path}: {what}; {fix}") from exc
    except MemoryError as exc:
        raise error(f"{path}: declares sizes too large to allocate (corrupt header?); {fix}") from exc
    except Exception as exc:
        detail = " ".join(str(exc).split())[:200]
        raise error(f"{path}: unreadable ({type(exc).__name__}{': ' + detail if detail else ''}); {fix}") from exc
