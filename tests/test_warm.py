"""The kernel shares of pool workers cover what a tuning chunk compiles."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from adnmesh.config import load_config
from adnmesh.tuning import TuningProblem
from adnmesh.tuning.warm import warm_share

ROOT = Path(__file__).resolve().parent.parent

#: in a process with an empty numba cache: warm the shares, then tune a chunk of SimBench
#: plants with both methods and report every compilation numba makes during the chunk
_PROBE = r"""
import json, sys
from numba.core import event
from adnmesh.config import load_config
from adnmesh.tuning.build import _tune_chunk, group_subsets, plant_chunks
from adnmesh.tuning.problem import TuningProblem, all_subsets
from adnmesh.tuning.warm import SHARES, warm_share

config = load_config(sys.argv[1])
problem = TuningProblem(config)
for share in SHARES:
    warm_share(problem, share)
groups = group_subsets(problem, all_subsets(list(config.der_ids())))
chunk = plant_chunks(groups, 148)[2][:12]
compiled = []


class Record(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__name__)

    def on_end(self, ev):
        pass


with event.install_listener("numba:compile", Record()):
    for method in ("global", "paper"):
        _tune_chunk((config, problem.constraints, method, chunk, True))
print(json.dumps(compiled))
"""


@pytest.mark.slow
def test_after_both_shares_a_tuning_chunk_compiles_nothing(tmp_path) -> None:
    """From an empty numba cache: once both shares ran, tuning SimBench plants (global
    search, paper path, area search, Find W, figures) compiles no kernel; so two workers
    that split the shares compile nothing twice."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", _PROBE, str(ROOT / "configs" / "simbench.yaml")],
                         env=env, capture_output=True, text=True, timeout=600, check=True)
    compiled = json.loads(out.stdout.strip().splitlines()[-1])
    assert compiled == [], f"compiled during the chunk: {sorted(set(compiled))}"


def test_an_unknown_share_is_an_error() -> None:
    problem = TuningProblem(load_config(ROOT / "configs" / "simbench.yaml"))
    with pytest.raises(ValueError, match="unknown share"):
        warm_share(problem, "everything")


@pytest.mark.parametrize("given", [None, "3"])
def test_pool_workers_start_with_one_blas_thread_unless_told(monkeypatch, given) -> None:
    """The pool's workers get OPENBLAS_NUM_THREADS=1 (a spawned worker reads it when it imports
    numpy); a value the caller set is kept, and the caller's environment is as it was after."""
    from adnmesh.tuning.build import _one_blas_thread_in_workers

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    if given is not None:
        monkeypatch.setenv("OPENBLAS_NUM_THREADS", given)
    with _one_blas_thread_in_workers():
        assert os.environ["OPENBLAS_NUM_THREADS"] == (given or "1")
    assert os.environ.get("OPENBLAS_NUM_THREADS") == given
