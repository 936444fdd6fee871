"""A non-editable install of the wheel runs ``adnmesh up`` (the agent programs ship inside it).

The wheel is built from a copy of the source tree (the build writes ``build/`` and an egg-info,
which must not land in the tree), without build isolation and without an index: the build backend
is the test environment's setuptools. It goes into a fresh venv with ``--no-deps``; the venv sees
this environment's site-packages through a ``.pth`` line, for numpy, zenoh and the rest, but not
the editable adnmesh in it: a plain path line in a ``.pth`` adds the directory to ``sys.path``
behind the venv's own site-packages and processes none of the ``.pth`` files in it, so the
editable finder is never installed. ``up`` runs with the working directory in ``tmp_path``, away
from the source tree.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import site
import subprocess
import sys
from pathlib import Path

import pytest

from up_runs import alive, descendants_of, write_case

REPO = Path(__file__).resolve().parent.parent
UP_TIMEOUT_S = 180
AGENT_MODULES = ("availability", "cpfc", "der", "measurement")
#: what the build must not see (top level of the tree only; caches anywhere)
_NOT_BUILT = {".venv", ".git", "build", "logs", "tables", "out", ".pytest_cache"}


def _ignore(directory: str, names: list[str]) -> set[str]:
    ignored = {n for n in names if n == "__pycache__" or n.endswith(".egg-info")}
    if Path(directory) == REPO:
        ignored |= _NOT_BUILT & set(names)
    return ignored


def _run(argv: list[str], **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False,
                            **kwargs)
    assert result.returncode == 0, f"{argv}\n{result.stdout}\n{result.stderr}"
    return result


def _run_up(argv: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run ``up`` to its end, bounded; on timeout end it and its agents by PID."""
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=UP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        agents = descendants_of(proc.pid)
        proc.kill()
        for pid in agents:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"adnmesh up did not exit within {UP_TIMEOUT_S} s:\n{err}")
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


@pytest.mark.slow
def test_installed_wheel_runs_up(tmp_path: Path):
    # the wheel, from a copy of the tree
    source, dist = tmp_path / "source", tmp_path / "dist"
    shutil.copytree(REPO, source, ignore=_ignore)
    _run([sys.executable, "-m", "pip", "wheel", "--isolated", "--no-deps", "--no-index",
          "--no-build-isolation", "--wheel-dir", str(dist), str(source)])
    (wheel,) = dist.glob("adnmesh-*.whl")

    # a fresh venv with the wheel alone (no byte code yet: that the agents write it proves where
    # they ran from) and this environment's dependencies behind it
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    python = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--isolated",
          "--no-deps", "--no-index", "--no-compile", str(wheel)])
    (venv_site,) = (venv / "lib").glob("python3.*/site-packages")
    (venv_site / "_test_dependencies.pth").write_text(
        "".join(f"{path}\n" for path in site.getsitepackages()))
    env = {k: v for k, v in os.environ.items()
           if k not in {"PYTHONPATH", "PYTHONHOME", "PYTHONDONTWRITEBYTECODE", "VIRTUAL_ENV"}}

    package = venv_site / "adnmesh"
    assert (package / "agents" / "der.py").is_file()
    where = json.loads(_run([str(python), "-c", (
        "import importlib.metadata as m, importlib.util as u, json, sys, adnmesh; print(json."
        "dumps([adnmesh.__file__, u.find_spec('adnmesh.agents.der').origin, str(m.distribution("
        "'adnmesh')._path), [type(f).__module__ for f in sys.meta_path]]))")],
        cwd=tmp_path, env=env).stdout)
    assert where[:3] == [str(package / "__init__.py"), str(package / "agents" / "der.py"),
                         str(venv_site / "adnmesh-0.1.0.dist-info")]
    assert not any("editable" in module for module in where[3]), where[3]
    tag = sys.implementation.cache_tag
    compiled = {f"{name}.{tag}.pyc" for name in AGENT_MODULES}
    assert not compiled & {p.name for p in package.glob("agents/__pycache__/*.pyc")}

    # a 12 s scenario of two wind turbines with its gain table, the working directory outside
    # the tree
    config, table = write_case(tmp_path)
    recording, summary = tmp_path / "run.mcap", tmp_path / "summary.json"
    result = _run_up([str(venv / "bin" / "adnmesh"), "up", str(config), "--table", str(table),
                      "--out", str(recording), "--summary-json", str(summary)],
                     cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr
    assert recording.stat().st_size > 0
    extra = json.loads(summary.read_text())["extra"]
    assert (extra["ended"], extra["agents"]) == ("finished", 5)
    # every agent program was run from the venv (up itself imports none of them)
    assert compiled <= {p.name for p in package.glob("agents/__pycache__/*.pyc")}
