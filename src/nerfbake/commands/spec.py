"""How a command is declared: a dataclass whose fields are its options (``option``), optionally a set of flags that
override a stage config's fields (``config_overrides``), and a ``run()`` that calls the library.

cli.py turns each such dataclass into an argparse parser: flag ``--max-views`` for field ``max_views``, the type from
the annotation, the help from the field. A Python caller runs the same command without a command line:
``OctreeInfo(tree="lego.npz").run()`` returns what ``--json`` prints.
"""
from __future__ import annotations

from dataclasses import MISSING, field
from typing import Any, ClassVar

from nerfbake.data.normalization import NORMALIZATIONS, NORMALIZE_HELP, TREE_NORMALIZE_HELP  # noqa: F401 (re-exported)
PRESETS = ("cpu-small", "paper")


def option(default: Any = MISSING, help: str = "", *, choices=None, positional: bool = False, group: str | None = None,
           metavar: str | None = None, flag: str | None = None):
    """One option of a command. No default: required. ``group``: one of the options sharing it must be given (and
    only one). ``flag``: a flag name other than the field's (e.g. ``--no-autoscale`` for a True default)."""
    return field(default=default, metadata={"help": help, "choices": choices, "positional": positional, "group": group,
                                            "metavar": metavar, "flag": flag})


def config_overrides(config: str, *names: str):
    """Flags that override fields of a stage config (``"module:Class"``, imported when the command's parser is built):
    their types, help and flag names come from that dataclass's fields; the values given arrive as a dict, the fields
    not given keep the preset's values."""
    return field(default_factory=dict, metadata={"config": config, "fields": names})


OVERWRITE = "replace an existing output (only once the new one is complete)"
JSON = "print one JSON object"


class Command:
    """A command: ``run()`` does the work and returns what ``--json`` prints (or None); ``text(result)`` is the human
    summary; ``exit_code(result)`` is 0 unless the command says otherwise."""
    name: ClassVar[str]  # "octree compress"
    help: ClassVar[str]

    def run(self) -> Any:
        raise NotImplementedError

    def text(self, result) -> str | None:
        """A command that returns a line (or lines) prints it; a dict or a list needs the command's own words."""
        return result if isinstance(result, str) else None

    def exit_code(self, result) -> int:
        return 0
