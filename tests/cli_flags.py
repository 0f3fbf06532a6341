"""Every command's flags as the parser declares them: ``{"octree compress": ["--band-bits", ...], ...}``.
``python -m tests.cli_flags > tests/cli_flags.json`` re-records them after a deliberate change of the CLI."""
from __future__ import annotations

import argparse
import json


def command_flags(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, list[str]]:
    out = {prefix.strip() or "nerfbake": sorted(s for a in parser._actions for s in a.option_strings)}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.update(command_flags(sub, f"{prefix} {name}"))
    return out


if __name__ == "__main__":
    from nerfbake.cli import build_parser

    print(json.dumps(command_flags(build_parser()), indent=1, sort_keys=True))
