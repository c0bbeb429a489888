"""A non-editable install (`pip install --prefix P .`, as colcon's ament_python install lays it
out) finds its own data in P/share/mapf_fleet: the default checkpoint of `mapf-fleet up`, the
protocol file of `mapf-fleet evaluate`, the launch file. Run from outside the checkout, with
PYTHONPATH naming the install."""

import glob
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
# what setup.py reads: copied so that the build leaves the work tree alone
SOURCES = ["setup.py", "setup.cfg", "package.xml", "resource", "mapf_fleet", "config", "models", "launch"]


def _installed_here() -> list[str]:
    """The files of mapf_fleet's distribution in the environment running the tests."""
    import importlib.metadata

    try:
        dist = importlib.metadata.distribution("mapf_fleet")
    except importlib.metadata.PackageNotFoundError:
        return []
    return sorted(str(dist.locate_file(f)) for f in dist.files or [])


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("install")
    source, prefix = tmp / "source", tmp / "prefix"
    source.mkdir()
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, source / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        elif path.is_file():
            shutil.copy2(path, source / name)
    before = _installed_here()
    # --ignore-installed: without it pip uninstalls the project's own (editable) mapf_fleet from
    # the running environment before installing into the prefix
    done = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                           "--ignore-installed", "--prefix", str(prefix), str(source)],
                          capture_output=True, text=True, timeout=600)
    assert _installed_here() == before, "the install into a prefix changed the running environment"
    assert done.returncode == 0, done.stderr[-3000:]
    site = glob.glob(str(prefix / "lib" / "python*" / "site-packages"))
    assert len(site) == 1, site
    # `up` and `evaluate` run from the install: on loopback, as every process the project starts
    env = dict(os.environ, PYTHONPATH=site[0], XDG_CACHE_HOME=str(tmp / "cache"),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    shutil.rmtree(source)  # nothing may be read from the copy the package was built from
    work = tmp / "elsewhere"
    work.mkdir()

    def run(*args, **kw):
        return subprocess.run([sys.executable, *args], cwd=work, env=env, capture_output=True, text=True,
                              timeout=300, **kw)

    return prefix, run, work


def test_installed_modules_find_the_share_directory(installed):
    prefix, run, _ = installed
    share = (prefix / "share" / "mapf_fleet").resolve()
    done = run("-c", "import json, mapf_fleet, mapf_fleet.paths as p, mapf_fleet.ros.launcher as up, "
                     "mapf_fleet.evaluation.protocol as proto; print(json.dumps({"
                     "'module': mapf_fleet.__file__, 'default': str(up.DEFAULT_CHECKPOINT), "
                     "'chosen': up.default_checkpoint(), 'protocol': str(proto.DEFAULT_CONFIG), "
                     "'launch': str(p.data_path('launch', 'fleet.launch.py')), 'cache': str(proto.DEFAULT_CACHE)}))")
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert Path(found["module"]).resolve().is_relative_to(prefix.resolve()), found
    assert Path(found["default"]) == share / "models" / "default.pt" and Path(found["default"]).is_file()
    assert Path(found["chosen"]).resolve().parent == share / "models"
    assert Path(found["protocol"]) == share / "config" / "evaluation" / "paper.yaml"
    assert Path(found["launch"]) == share / "launch" / "fleet.launch.py" and Path(found["launch"]).is_file()
    assert not Path(found["cache"]).is_relative_to(prefix.resolve()), "cache inside the install prefix"


def test_installed_up_help_and_missing_checkpoint(installed):
    prefix, run, _ = installed
    done = run("-m", "mapf_fleet.cli", "up", "--help")
    assert done.returncode == 0 and "--checkpoint" in done.stdout, done.stderr
    # the console script pip wrote (a wheel install puts it in <prefix>/bin)
    script = prefix / "bin" / "mapf-fleet"
    assert script.is_file()
    done = run(str(script), "up", "--help")
    assert done.returncode == 0 and "--checkpoint" in done.stdout, done.stderr
    # without any checkpoint in the installed models/, `up` names the installed folder, exit 2
    models = prefix / "share" / "mapf_fleet" / "models"
    for checkpoint in models.glob("*.pt"):
        checkpoint.unlink()
    done = run("-m", "mapf_fleet.cli", "up")
    assert done.returncode == 2, done.stderr
    assert str(models) in done.stderr, done.stderr


def test_installed_evaluate_reads_the_installed_protocol(installed):
    prefix, run, work = installed
    out = work / "eval.json"
    done = run("-m", "mapf_fleet.cli", "evaluate", "--checkpoint", "heuristic", "--sizes", "40", "--agents", "4",
               "--instances", "2", "--no-references", "--quiet", "--json", str(out))
    assert done.returncode == 0, done.stderr
    assert "| Success Rate" in done.stdout
    metadata = json.loads(out.read_text())["metadata"]
    assert Path(metadata["protocol_file"]) == (prefix / "share" / "mapf_fleet" / "config" / "evaluation"
                                               / "paper.yaml").resolve()
