"""An output folder that refuses writes is one line and exit 2, never a
``PermissionError`` traceback (issue #34 item 5).

The tests run as root, where ``chmod 0555`` stops nothing, so a folder that
refuses writes is made with ``chattr +i`` (immutable: EPERM for root too; plain
``chmod 0555`` when not root). ``os.access`` sees through that, so
``atomic.check_writable`` refuses most outputs up front; the writes that
slipped past it (a forward Jacobian, a recording's log in an existing folder,
figures, the Monte Carlo validation's folder and tables) are also checked
where ``os.access`` says yes and the write still fails: a folder of sysfs,
which root may "write" by access(2) and whose files refuse creation (EACCES).
"""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MC_DATA = ROOT / "FluoTomo" / "FluoTomoLib" / "montecarlo" / "data"


@pytest.fixture
def locked(tmp_path):
    """An existing, empty folder that refuses new files (root included)."""
    d = tmp_path / "locked"
    d.mkdir()
    if os.geteuid() == 0:
        if shutil.which("chattr") is None:
            pytest.skip("root without chattr: no folder refuses root's writes here")
        r = subprocess.run(["chattr", "+i", str(d)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"chattr +i not supported on {tmp_path}: {r.stderr.strip()}")
        undo = ["chattr", "-i", str(d)]
    else:
        d.chmod(0o555)
        undo = ["chmod", "755", str(d)]
    with pytest.raises(OSError):
        (d / "probe").write_text("x")
    yield d
    subprocess.run(undo, check=True)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A small mesh with its optodes, and a synthetic light data set."""
    import numpy as np

    import forkserver
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu

    d = tmp_path_factory.mktemp("perm")
    write_vtu(mesh_labelmap_structured(np.ones((10, 10, 10), np.int32), np.ones(3),
                                       np.array([-4.5, -4.5, -9.5]), 2.0), d / "m.vtu")
    (d / "s.csv").write_text("0,0,0\n")
    (d / "d.csv").write_text("3,0,0\n")
    r = forkserver.fluo("calib", "synth-light", "--out", d / "light", "--json")
    assert r.returncode == 0, r.stderr
    return d


def _commands(inputs, out):
    """Each writing command whose write slipped past the up-front check, with
    ``out`` as its output (a file name or a folder)."""
    return {
        "forward --jacobian-out": ["forward", "--mesh", inputs / "m.vtu", "--mua", "0.01",
                                   "--musp", "1", "--sources", inputs / "s.csv", "--detectors",
                                   inputs / "d.csv", "--jacobian-out", out / "J.npy"],
        "calib illumination --out": ["calib", "illumination", inputs / "light" / "illumination",
                                     "--axisymmetric", "--out", out],
        "validate mc --out": ["validate", "mc", "--mc-in", MC_DATA / "halfspace_n137.json",
                              "--mesh-level", "test", "--boundary", "fresnel", "--out", out],
        "record --out": ["record", "--out", out, "--seconds", "0.5", "--fps", "5", "--width",
                         "64", "--height", "48", "--seed", "0"],
    }


def _one_line_exit_2(r, needle):
    """Exit 2, one error line (after any progress lines: stderr is not a terminal)."""
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in lines if "error" in ln]
    assert errors == lines[-1:] and lines[-1].startswith("fluo: error: "), lines
    assert needle in lines[-1], lines


@pytest.mark.parametrize("what", ["forward --jacobian-out", "calib illumination --out",
                                  "validate mc --out", "record --out"])
def test_a_folder_that_refuses_writes_is_one_line(what, locked, inputs, fluo):
    r = fluo(*_commands(inputs, locked)[what], "--json")
    _one_line_exit_2(r, str(locked))
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(os.geteuid() != 0 or not os.path.isdir("/sys/kernel")
                    or not os.access("/sys/kernel", os.W_OK),
                    reason="needs root and sysfs (access(2) says writable, creating fails)")
@pytest.mark.parametrize("what", ["forward --jacobian-out", "calib illumination --out",
                                  "validate mc --out"])
def test_writes_that_fail_after_the_check_passed_are_one_line(what, inputs, fluo):
    """EACCES at the write itself: atomic's writers and the validation's folder
    turn it into the same one line (it was ``fluo: internal error:
    PermissionError``)."""
    out = Path("/sys/kernel")
    r = fluo(*_commands(inputs, out)[what], "--json")
    _one_line_exit_2(r, "cannot write here")
