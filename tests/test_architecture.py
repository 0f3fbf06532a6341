"""The package's layering, read from the modules' own import statements (ast, nothing imported):

* kernels know no route: ``kernels/`` imports nothing from ``octree/``, ``smerf/``, ``teacher/``, the pipeline or
  the CLI (the SMERF grid kernel takes the 8-bit round trip from ``render/quantize.py``);
* render math knows no files, models or routes: ``render/`` imports only ``render/`` (and ``errors``);
* the two routes stand apart: ``octree/`` never imports ``smerf/`` and the reverse;
* the library knows no command line: only ``cli.py`` imports argparse;
* routes read a teacher through its artifact (``teacher/run.py``), never through its trainer (``teacher/train.py``),
  and a SMERF student through ``smerf/run.py`` outside the trainer itself.
"""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "nerfbake"


def imports_of(path: Path) -> set[str]:
    """Every ``nerfbake.*`` module a file imports, at top level or inside functions."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("nerfbake"):
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names if a.name.startswith("nerfbake"))
    return names


def modules_in(package: str) -> dict[str, set[str]]:
    return {str(p.relative_to(PACKAGE)): imports_of(p) for p in sorted((PACKAGE / package).rglob("*.py"))}


def offenders(package: str, forbidden) -> list[str]:
    return [f"{mod} imports {name}" for mod, names in modules_in(package).items() for name in sorted(names)
            if forbidden(name)]


def test_kernels_import_no_route():
    routes = ("nerfbake.octree", "nerfbake.smerf", "nerfbake.teacher", "nerfbake.pipeline", "nerfbake.cli")
    assert offenders("kernels", lambda n: n.startswith(routes)) == []


def test_render_math_imports_only_render():
    assert offenders("render", lambda n: not n.startswith(("nerfbake.render", "nerfbake.errors"))) == []


def test_the_two_routes_stand_apart():
    assert offenders("octree", lambda n: n.startswith("nerfbake.smerf")) == []
    assert offenders("smerf", lambda n: n.startswith("nerfbake.octree")) == []


ARTIFACT_NAMES = {"nerfbake.teacher.train": {"load_teacher", "config_from_dict", "CHECKPOINT", "CONFIG"},
                  "nerfbake.smerf.distill": {"load_student", "config_from_dict", "DistillConfig", "distill_preset",
                                             "CHECKPOINT", "CONFIG"}}


def test_routes_read_teachers_and_students_through_their_artifacts():
    assert offenders("octree", lambda n: n == "nerfbake.teacher.train") == []
    assert offenders("smerf", lambda n: n == "nerfbake.teacher.train") == []
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module in ARTIFACT_NAMES:
                taken = {a.name for a in node.names} & ARTIFACT_NAMES[node.module]
                if taken:
                    wrong.append(f"{path.relative_to(PACKAGE)} takes {sorted(taken)} from the trainer {node.module}")
    assert wrong == []


def test_the_library_knows_no_command_line():
    parsers = [str(p.relative_to(PACKAGE)) for p in sorted(PACKAGE.rglob("*.py"))
               if any(isinstance(n, (ast.Import, ast.ImportFrom)) and "argparse" in
                      ([a.name for a in n.names] if isinstance(n, ast.Import) else [n.module])
                      for n in ast.walk(ast.parse(p.read_text())))]
    assert parsers == ["cli.py"]
