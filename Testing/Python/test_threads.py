"""Thread pools set on purpose (fluoguide/threads.py): the choice, its sources,
and that it reaches BLAS, MKL and numba in a fresh process."""

import json
import os
import subprocess
import sys

import pytest

from fluoguide.errors import FluoInputError
from fluoguide.threads import cpu_count, resolve_threads

PROBE = r"""
import json, sys
from fluoguide.threads import configure_threads
info = configure_threads(sys.argv[1] if sys.argv[1] != "-" else None)
import numpy, numba
from threadpoolctl import threadpool_info
from FluoTomoLib.fem.pardiso import mkl_pardiso
mkl_pardiso()                              # MKL is loaded late, for PARDISO
pools = {i["internal_api"]: i["num_threads"] for i in threadpool_info()}
print(json.dumps({"info": info, "pools": pools, "numba": numba.get_num_threads()}))
"""


def _probe(arg, env_value=None):
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                        "NUMBA_NUM_THREADS", "FLUO_THREADS")}
    if env_value is not None:
        env["FLUO_THREADS"] = env_value
    r = subprocess.run([sys.executable, "-c", PROBE, arg], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_sources_and_values(monkeypatch):
    monkeypatch.delenv("FLUO_THREADS", raising=False)
    assert resolve_threads() == (1, "default")
    assert resolve_threads(3) == (3, "argument")
    assert resolve_threads("auto") == (cpu_count(), "argument")
    assert resolve_threads("system") == (None, "argument")
    monkeypatch.setenv("FLUO_THREADS", "2")
    assert resolve_threads() == (2, "FLUO_THREADS")
    assert resolve_threads("1") == (1, "argument")        # the option beats the variable
    for bad in ("0", "-2", "many", "1.5"):
        with pytest.raises(FluoInputError, match="threads"):
            resolve_threads(bad)
    monkeypatch.setenv("FLUO_THREADS", "lots")
    with pytest.raises(FluoInputError, match="FLUO_THREADS"):
        resolve_threads()


def test_default_reaches_every_library_in_a_fresh_process():
    out = _probe("-")
    assert out["info"]["threads"] == 1 and out["info"]["source"] == "default"
    assert out["numba"] == 1
    assert out["pools"] and set(out["pools"].values()) == {1}, out["pools"]


@pytest.mark.skipif(cpu_count() < 2, reason="needs two cores")
def test_environment_variable_and_system():
    out = _probe("-", env_value="2")
    assert out["info"] == {**out["info"], "threads": 2, "source": "FLUO_THREADS"}
    assert out["numba"] == 2 and set(out["pools"].values()) == {2}
    untouched = _probe("system")
    assert untouched["info"]["threads"] is None and untouched["info"]["settings"] is None


def test_cli_option_and_bad_value(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "FLUO_THREADS"}
    out = tmp_path / "ph"
    r = subprocess.run([sys.executable, "-m", "fluoapp", "--threads", "0", "phantom",
                        "cylinder-tube", "--out", str(out)],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--threads" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    env["FLUO_THREADS"] = "none"
    r = subprocess.run([sys.executable, "-m", "fluoapp", "phantom", "cylinder-tube", "--out",
                        str(out)], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "FLUO_THREADS" in r.stderr and not out.exists()


def test_library_threads_are_not_ftetwild_threads():
    """`fluo --threads` (the libraries) and `fluo mesh --threads` (fTetWild) are two
    options: one must not overwrite the other in the parsed arguments."""
    from fluoapp.cli import build_parser

    args = build_parser().parse_args(["--threads", "2", "mesh", "labels.nrrd", "--out", "m",
                                      "--threads", "4"])
    assert (args.library_threads, args.threads) == ("2", 4)
    args = build_parser().parse_args(["mesh", "labels.nrrd", "--out", "m", "--threads", "4"])
    assert args.library_threads is None
