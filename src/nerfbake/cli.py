"""``nerfbake <verb>``: the command line of ``nerfbake.commands``, one parser per command dataclass.

Errors caused by input (missing files, bad values) print one line ``error: ...`` and exit with status 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import sys
import typing
from typing import Any

from nerfbake import __version__
from nerfbake.commands import COMMANDS, GROUPS
from nerfbake.commands.spec import Command
from nerfbake.errors import NerfbakeError
from nerfbake.signals import terminate_like_ctrl_c


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """Every command's parser. Given ``argv``, only the command it names gets its options: the other commands' stage
    configs (and torch with them) are not imported just to start."""
    parser = argparse.ArgumentParser(prog="nerfbake", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    parser.add_argument("--version", action="version", version=f"nerfbake {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    groups: dict[str, Any] = {}
    chosen = named_command(argv) if argv is not None else None
    for cls in COMMANDS:
        *group, verb = cls.name.split()
        where = commands
        if group:
            if group[0] not in groups:
                groups[group[0]] = commands.add_parser(group[0], help=GROUPS[group[0]]).add_subparsers(
                    dest=f"{group[0]}_command", required=True)
            where = groups[group[0]]
        sub = where.add_parser(verb, help=cls.help, description=cls.help)
        sub.set_defaults(command_class=cls)
        if argv is None or chosen is cls:
            add_options(sub, cls)
    return parser


def named_command(argv: list[str]) -> type[Command] | None:
    """The command the words of ``argv`` name (``octree compress ...`` -> OctreeCompress), if any."""
    words = [a for a in argv if not a.startswith("-")]
    for cls in COMMANDS:
        parts = cls.name.split()
        if words[:len(parts)] == parts:
            return cls
    return None


def add_options(parser: argparse.ArgumentParser, cls: type[Command]) -> None:
    """One argparse argument per field of the command's dataclass; a ``config_overrides`` field becomes one optional
    flag per named field of its stage config (default None: the preset's value stays)."""
    hints = typing.get_type_hints(cls)
    exclusive: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if "config" in f.metadata:
            module, name = f.metadata["config"].split(":")
            config = getattr(importlib.import_module(module), name)
            fields, config_hints = {c.name: c for c in dataclasses.fields(config)}, typing.get_type_hints(config)
            for n in f.metadata["fields"]:
                add_option(parser, n, config_hints[n], fields[n].metadata, fields[n].default, f"{f.name}:{n}", None)
            continue
        group = f.metadata.get("group")
        if group and group not in exclusive:
            exclusive[group] = parser.add_mutually_exclusive_group(required=True)
        add_option(exclusive.get(group, parser), f.name, hints[f.name], f.metadata, f.default, f.name, f.default)


def add_option(parser, name: str, hint, meta, field_default, dest: str, default) -> None:
    kind = next((t for t in typing.get_args(hint) if t is not type(None)), hint)
    kw = {k: meta[k] for k in ("help", "choices", "metavar") if meta.get(k)}
    if meta.get("positional"):
        parser.add_argument(dest, type=kind, **{"metavar": meta.get("flag"), **kw})
        return
    flag = meta.get("flag") or "--" + name.replace("_", "-")
    if kind is bool:  # a switch to the opposite of the field's default
        parser.add_argument(flag, dest=dest, action="store_const", const=not field_default, default=default, **kw)
        return
    if "choices" not in kw:
        kw.setdefault("metavar", name.upper())  # not the dest ("overrides:grid")
    if default is dataclasses.MISSING:
        parser.add_argument(flag, dest=dest, type=kind, required=True, **kw)
    else:
        parser.add_argument(flag, dest=dest, type=kind, default=default, **kw)


def command_from(args: argparse.Namespace) -> Command:
    """The command dataclass filled from parsed arguments (override flags not given are left out)."""
    cls, values, kwargs = args.command_class, vars(args), {}
    for f in dataclasses.fields(cls):
        if "config" in f.metadata:
            given = {n: values[f"{f.name}:{n}"] for n in f.metadata["fields"]}
            kwargs[f.name] = {n: v for n, v in given.items() if v is not None}
        else:
            kwargs[f.name] = values[f.name]
    return cls(**kwargs)


def show(command: Command, result) -> None:
    """``--json``: the result as one JSON object; otherwise the command's own summary."""
    if getattr(command, "json", False):
        print(json.dumps(result, indent=2))
    elif (text := command.text(result)) is not None:
        print(text)


def main(argv: list[str] | None = None) -> int:
    """Exit 0 on success, 2 with one ``error: ...`` line for bad input (the project's errors, missing files, a busy
    port), 130 on Ctrl-C; anything else is a bug, reported in one line as such (``--debug``: the traceback)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    terminate_like_ctrl_c()
    try:
        command = command_from(args)
        result = command.run()
        show(command, result)
        return command.exit_code(result)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (NerfbakeError, ValueError, OSError) as exc:
        if args.debug:
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 -- the last line of defence against a traceback
        if args.debug:
            raise
        print(f"error: unexpected {type(exc).__name__}: {_one_line(exc)} -- this is a bug in nerfbake; rerun with "
              "--debug for the traceback and report it", file=sys.stderr)
        return 1


def _one_line(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
        text = f"{exc.filename}: {text}"
    return " ".join(text.split())


if __name__ == "__main__":
    sys.exit(main())
