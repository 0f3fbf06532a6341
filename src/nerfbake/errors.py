"""The project's error types: one per stage, all :class:`NerfbakeError`, whose ``str`` is one line that names the
file and says what to do. The CLI prints that line and exits 2 (``--debug`` shows the traceback); anything else
reaching the CLI is a bug in nerfbake and is reported as one."""
import json
from contextlib import contextmanager
from pathlib import Path


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


def read_folder_config(folder, name: str, what: str, made_by: str, is_one) -> dict:
    """The JSON config ``folder/name`` of an artifact folder, checked to describe ``what`` (``is_one(meta)``); a
    missing, unreadable or other-kind config is a :class:`RunFolderError` naming it and ``made_by``, the command
    whose ``--out`` folder is expected."""
    path = Path(folder) / name
    if not path.is_file():
        raise RunFolderError(f"{path}: missing; {folder} is not a {what} ({made_by} --out)")
    with reading(path, RunFolderError, f"pass the --out folder of {made_by}, or run it again with this version"):
        meta = json.loads(path.read_text())
    if not isinstance(meta, dict) or not is_one(meta):
        kind = meta.get("kind", "different kind of") if isinstance(meta, dict) else "non-object"
        raise RunFolderError(f"{path}: not a {what} (it holds a {kind} config); pass the --out folder of {made_by}")
    return meta
