"""What a user installs: a wheel built from this tree carries the viewer's static files and, installed into a fresh
virtual environment, gives a working ``nerfbake`` command (its dependencies lent from this environment, so the
test costs seconds and no downloads)."""
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

from tests.conftest import shared_data

ROOT = Path(__file__).resolve().parents[1]


def test_a_wheel_installs_into_a_fresh_venv_and_runs(tmp_path):
    fern = shared_data("fern")
    dist, tree = tmp_path / "dist", tmp_path / "tree"  # a copy, so the build leaves nothing in the checkout
    shutil.copytree(ROOT, tree, ignore=shutil.ignore_patterns(".venv", "outputs", "build", "dist", ".git", "*.egg-info",
                                                              "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", dist, tree],
                   check=True, capture_output=True, cwd=tmp_path)
    wheel = next(dist.glob("nerfbake-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for static in ("index.html", "main.js", "smerf.js", "octree.js"):
        assert f"nerfbake/viewer/static/{static}" in names, static
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    site = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    # the dependencies (torch, warp, ...) from this environment, appended after the fresh site-packages; this
    # environment's editable nerfbake is not among them (its .pth files are not processed from a plain path entry)
    (site / "_deps_from_test_env.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target", site, wheel],
                   check=True, capture_output=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    where = subprocess.run([py, "-c", "import nerfbake, pathlib; print(pathlib.Path(nerfbake.__file__).resolve())"],
                           check=True, capture_output=True, text=True, cwd=tmp_path, env=env).stdout.strip()
    assert Path(where).is_relative_to(site.resolve()), where  # the installed wheel, not this checkout
    exe = [py, "-m", "nerfbake"]
    version = subprocess.run([*exe, "--version"], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert version.returncode == 0 and version.stdout.strip().startswith("nerfbake "), version.stderr
    info = subprocess.run([*exe, "data", "info", fern, "--json"], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["num_images"] == 20
