"""Work that will not fit is refused before it starts (issue #34 item 5).

``fluo phantom cylinder-tube --voxel-mm 0.1`` (inside the documented 0.1..5 mm)
ran out of memory under the fuzz's cap and ended in a ``MemoryError``
traceback: exit 1. Each command runs here as a child of the fork server with
a data-segment limit (``RLIMIT_DATA``, the same cap a batch system or the fuzz
sets); the estimate (fluoguide/memory.py and the measured bytes per voxel,
tetrahedron and node beside each caller) refuses it in about a second with one
line: the estimate in GB, what is available and how to lower it. The same
commands at the sizes the project itself runs still run under the fuzz's cap.
"""

import resource
import subprocess
import sys

import pytest


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from small_cases import write_own_scene

    d = tmp_path_factory.mktemp("mem")
    write_own_scene(d)
    return d


def _refused(r, field, hint):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and r.stdout == "", r.stderr
    assert len(lines) == 1 and lines[0].startswith(f"fluo: error: {field}: "), lines
    assert " GB of memory, " in lines[0] and " GB are available: " in lines[0], lines
    assert hint in lines[0], lines
    return lines[0]


def test_phantom_at_0_1_mm_is_refused_with_the_voxel_size_that_fits(tmp_path, fluo):
    r = fluo("phantom", "cylinder-tube", "--voxel-mm", "0.1", "--out", tmp_path / "ph",
             "--json", memory_limit_mb=3072)
    line = _refused(r, "voxel_mm", "use --voxel-mm 0.")
    assert "171 million voxels) needs about 13.7 GB" in line, line
    assert r.seconds < 10 and r.peak_mb < 1000 and not (tmp_path / "ph").exists()
    # the size it proposes runs under the same cap (the fuzz's base runs at 2 mm)
    r = fluo("phantom", "cylinder-tube", "--voxel-mm", "2", "--out", tmp_path / "ok", "--json",
             memory_limit_mb=3072)
    assert r.returncode == 0, r.stderr


def test_structured_and_quality_meshes_are_refused_before_meshing(scene, tmp_path, fluo):
    r = fluo("mesh", scene / "labels.nrrd", "--out", tmp_path / "m.vtu", "--size", "0.2",
             "--fast", "--json", memory_limit_mb=1000)
    assert "structured mesh of 4.2 million tetrahedra" in _refused(
        r, "size_mm", "choose a larger element size"), r.stderr
    r = fluo("mesh", scene / "labels.nrrd", "--out", tmp_path / "m.vtu", "--size", "0.4",
             "--json", memory_limit_mb=1000)
    assert "the quality mesh (3.6 million tetrahedra" in _refused(
        r, "size_mm", "choose a larger element size or an roi"), r.stderr
    assert not (tmp_path / "m.vtu").exists()
    r = fluo("mesh", scene / "labels.nrrd", "--out", tmp_path / "m.vtu", "--size", "2",
             "--fast", "--json", memory_limit_mb=1000)
    assert r.returncode == 0, r.stderr


def test_simulation_is_refused_once_its_mesh_is_known(scene, tmp_path, fluo):
    r = fluo("tomo", "simulate", "--labels", scene / "labels.nrrd", "--optics",
             scene / "optics.json", "--yield", "7:0.0026", "--accuracy", "fine", "--out",
             tmp_path / "acq", "--json", memory_limit_mb=300)
    assert "the diffusion model on " in _refused(r, "size_mm", "use accuracy 'fast'"), r.stderr
    assert not (tmp_path / "acq").exists()


def test_reconstruction_counts_its_jacobian():
    from FluoTomoLib.tomography.simulate import RECON_BYTES_PER_NODE, check_fem_memory

    from fluoguide.errors import FluoInputError
    from fluoguide.memory import available_bytes

    # 10 TB of Jacobian does not fit anywhere; the same mesh without it does
    with pytest.raises(FluoInputError, match=r"size_mm: the diffusion model on 50,000 nodes "
                                             r"\(0.8 mm elements\) and its 10000.0 GB Jacobian"):
        check_fem_memory(50_000, 1e13, 0.8, per_node=RECON_BYTES_PER_NODE)
    assert available_bytes() > RECON_BYTES_PER_NODE * 50_000
    check_fem_memory(50_000, 0.0, 0.8, per_node=RECON_BYTES_PER_NODE)


def test_available_memory_counts_the_data_segment_limit():
    code = ("import resource; resource.setrlimit(resource.RLIMIT_DATA, (2 << 30, 2 << 30)); "
            "from fluoguide.memory import available_bytes; print(available_bytes())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert 0 < int(out.stdout) <= 2 << 30
    from fluoguide.memory import available_bytes

    if resource.getrlimit(resource.RLIMIT_DATA)[0] == resource.RLIM_INFINITY:
        assert available_bytes() > 2 << 30


_FREED = """
import sys
import numpy as np
from fluoguide.memory import hand_back_large_blocks
def rss():
    return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) * 1024
set_ = hand_back_large_blocks() if sys.argv[1] == "1" else None
base, keep = rss(), []
for _ in range(6):
    a = np.ones(3 << 20)       # 24 MB, freed below
    keep.append(np.ones(1024))  # a small block after it on the heap
    del a
print(set_, (rss() - base) / 1e6)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_freed_large_arrays_leave_the_process():
    """The CLI's allocator setting (``memory.hand_back_large_blocks``): a 24 MB array
    freed, with small blocks allocated after it, gives its pages back; glibc's default
    (its threshold raised by the first such array freed) keeps one on the heap, where
    the peak resident memory counts it after it is gone."""
    runs = {flag: subprocess.run([sys.executable, "-c", _FREED, flag], capture_output=True,
                                 text=True, check=True).stdout.split()
            for flag in ("0", "1")}
    assert runs["1"][0] == "True"
    assert float(runs["1"][1]) < 5.0, runs
    assert float(runs["0"][1]) > 20.0, runs          # the default: what this changes
