"""The package's layering, read from the modules' own import statements (ast, nothing imported):

* kernels know no route: ``kernels/`` imports nothing from ``octree/``, ``smerf/``, ``teacher/``, the pipeline or
  the CLI (the SMERF grid kernel takes the 8-bit round trip from ``render/quantize.py``);
* render math knows no files, models or routes: ``render/`` imports only ``render/`` (and ``errors``);
* the two routes stand apart: ``octree/`` never imports ``smerf/`` and the reverse;
* the library knows no command line: only ``cli.py`` imports argparse;
* no import cycles among the modules' top-level imports, and no imports inside functions except the lazy ones
  named in ``LAZY_IMPORTS`` (heavy or optional dependencies) and the modules in ``LAZY_MODULES`` (commands, doctor);
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


# Imports inside functions, each for one reason: an optional or heavy dependency that only its feature needs.
LAZY_IMPORTS = {
    "pycolmap": "structure from motion (nerfbake process)", "mitsuba": "nerfbake synth's renderer",
    "av": "video intake (process --video)", "scipy": "SciPy's KD-tree and Laplacian, for two functions",
    "warp": "the kernels' JIT, loaded at the first launch", "matplotlib": "the report's figures",
    "playwright": "the headless browser of view --benchmark and the viewer tests",
    "torch.utils.tensorboard": "--tensorboard only",
    "imageio": "atomic.write_image: the CLI imports atomic at start-up, and imageio brings numpy (~90 ms)",
}
# Modules whose imports stay where they are used: the commands (each imports the library when it runs, so that
# ``nerfbake --help`` starts at once) and doctor (it reports a missing dependency instead of failing to start, so it
# imports what it checks only inside the check).
LAZY_MODULES = {"doctor.py", "commands/"}


def module_level_imports(path: Path) -> set[str]:
    return {n.module for n in ast.parse(path.read_text()).body
            if isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("nerfbake")}


def test_imports_inside_functions_are_only_the_lazy_ones():
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = str(path.relative_to(PACKAGE))
        if relative in LAZY_MODULES or any(relative.startswith(m) for m in LAZY_MODULES if m.endswith("/")):
            continue
        for fn in ast.walk(ast.parse(path.read_text())):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for n in ast.walk(fn):
                    if isinstance(n, (ast.Import, ast.ImportFrom)):
                        names = [a.name for a in n.names] if isinstance(n, ast.Import) else [n.module]
                        wrong += [f"{path.relative_to(PACKAGE)}:{n.lineno} imports {m} in {fn.name}" for m in names
                                  if m not in LAZY_IMPORTS and m.split(".")[0] not in LAZY_IMPORTS]
    assert wrong == []


def test_no_import_cycles():
    graph = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        graph[name] = module_level_imports(path)
    cycles = []

    def visit(node, stack):
        if node in stack:
            cycles.append(" -> ".join(stack[stack.index(node):] + [node]))
            return
        if node in done:
            return
        for dep in sorted(graph.get(node, ())):
            visit(dep, stack + [node])
        done.add(node)

    done: set[str] = set()
    for module in sorted(graph):
        visit(module, [])
    assert cycles == []


def test_every_public_function_of_the_math_and_the_routes_says_what_it_does():
    missing = [f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name}"
               for package in ("kernels", "render", "octree", "smerf") for path in sorted((PACKAGE / package).rglob("*.py"))
               for node in ast.parse(path.read_text()).body
               if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_")
               and not ast.get_docstring(node)]
    assert missing == []
