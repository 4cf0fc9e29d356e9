"""Figures, meshes, calibration files and data sets written as a whole: a
``kill -9`` at any moment leaves the old file or the new one, never a 0-byte or
truncated file at the final name, and the next write clears the debris
(issue #21: kill -9 of ``fluo demo`` left a 0-byte ``phantoms.png``, of
``fluo mesh`` a truncated ``out.vtu.tmp.vtu``)."""

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fluoguide import atomic
from fluoguide.errors import FluoInputError

ROOT = Path(__file__).resolve().parents[2]
TREE = [str(ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")]

# A child that rewrites a figure, a mesh and a calibration file in a loop, each
# version complete and numbered, so a SIGKILL lands in the middle of some write.
WRITER = textwrap.dedent("""
    import sys
    sys.path[:0] = {tree!r}
    import numpy as np
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from fluoguide import atomic
    from FluoCalibLib.radiometry.scene import write_calibration_json
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu

    out = {out!r}
    labels = np.ones((14, 14, 14), np.int32)
    mesh = mesh_labelmap_structured(labels, np.ones(3), np.zeros(3), 1.0)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.imshow(np.random.default_rng(0).random((300, 300)))
    payload = list(range(20000))
    print("ready", flush=True)
    k = 0
    while True:
        k += 1
        ax.set_title(f"version {{k}}")
        atomic.save_figure(fig, out + "/figure.png", dpi=100)
        write_vtu(mesh, out + "/mesh.vtu", point_data={{"k": np.full(mesh.n_nodes, float(k))}})
        write_calibration_json(out + "/calibration.json", "FluoGuide.Radiometry",
                               {{"version": k, "payload": payload}})
""")


def _check_outputs(out, n_elements):
    """Every final name is absent or complete and readable."""
    from PIL import Image

    from FluoTomoLib.meshing.vtu_io import read_vtu

    png = out / "figure.png"
    if png.exists():
        with Image.open(png) as im:
            im.load()                                  # decodes every byte
            assert im.size[0] > 100
    vtu = out / "mesh.vtu"
    if vtu.exists():
        mesh = read_vtu(vtu)
        assert mesh.n_elements == n_elements
        assert len(mesh.meta["point_data"]["k"]) == mesh.n_nodes
    cal = out / "calibration.json"
    if cal.exists():
        doc = json.loads(cal.read_text())
        assert doc["Other"] == {"kept": True}          # the other calibrations survive
        if "Radiometry" in doc:                         # a new version, whole
            assert len(doc["Radiometry"]["payload"]) == 20000
    visible = [p.name for p in out.iterdir() if not p.name.startswith(".")]
    assert set(visible) <= {"figure.png", "mesh.vtu", "calibration.json"}, visible


def test_kill_9_at_random_moments_leaves_old_or_new_files(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "calibration.json").write_text(json.dumps({"Other": {"kept": True}}))
    rng = random.Random(21)
    code = WRITER.format(tree=TREE, out=str(out))
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

    n_el = mesh_labelmap_structured(np.ones((14, 14, 14), np.int32), np.ones(3), np.zeros(3),
                                    1.0).n_elements
    kills = 0
    for attempt in range(6):
        p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "ready", p.stderr.read()
        time.sleep(rng.uniform(0.3, 2.0))            # some writes done, one under way
        p.send_signal(signal.SIGKILL)
        p.wait(30)
        kills += p.returncode == -signal.SIGKILL
        _check_outputs(out, n_el)
    assert kills == 6
    debris = [p.name for p in out.iterdir() if p.name.startswith(".")]
    # the next complete write of each file clears the debris of killed writers
    from FluoCalibLib.radiometry.scene import write_calibration_json
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    atomic.save_figure(fig, out / "figure.png")
    plt.close(fig)
    write_vtu(mesh_labelmap_structured(np.ones((3, 3, 3), np.int32), np.ones(3), np.zeros(3), 1.0),
              out / "mesh.vtu")
    write_calibration_json(out / "calibration.json", "FluoGuide.Radiometry", {"version": 0})
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [], debris
    assert json.loads((out / "calibration.json").read_text())["Other"] == {"kept": True}


def test_killed_writer_leaves_hidden_debris_only_and_a_folder_set_stays_whole(tmp_path):
    """Killed after its temporary file is complete but before the rename, and
    in the middle of a data set: the final names hold the old content."""
    from FluoCalibLib.radiometry.camera_response import Frame, load_stack, write_stack

    target = tmp_path / "fig.png"
    target.write_bytes(b"old")
    stack = tmp_path / "stack"
    old = [Frame(np.full((8, 8), 100.0), 0.01, "light"), Frame(np.full((8, 8), 10.0), 0.01, "dark")]
    write_stack(stack, old, {"version": 1})
    code = textwrap.dedent(f"""
        import os, sys
        sys.path[:0] = {TREE!r}
        import numpy as np
        from fluoguide import atomic
        from FluoCalibLib.radiometry.camera_response import Frame, write_stack
        which = sys.argv[1]
        if which == "file":
            os.fsync = lambda fd: os._exit(9)         # the temporary file is written: die
            atomic.write_bytes({str(target)!r}, b"new" * 1000)
        else:
            import cv2
            real, n = cv2.imwrite, [0]
            def imwrite(path, img):                   # die after the first new image
                if n[0] == 1:
                    os._exit(9)
                n[0] += 1
                return real(path, img)
            cv2.imwrite = imwrite
            new = [Frame(np.full((8, 8), 200.0 + k), 0.02, "light") for k in range(3)]
            write_stack({str(stack)!r}, new, {{"version": 2}})
    """)
    for which in ("file", "set"):
        r = subprocess.run([sys.executable, "-c", code, which], capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 9, r.stderr
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".fig.png.tmp-")]
    frames, meta = load_stack(stack)                  # the old set, whole
    assert meta["version"] == 1 and len(frames) == 2 and frames[0].image.max() == 100
    atomic.write_bytes(target, b"newer")              # a later write clears the debris
    assert target.read_bytes() == b"newer"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".fig.png.tmp-")]
    write_stack(stack, old[:1], {"version": 3})
    assert load_stack(stack)[1]["version"] == 3
    assert not [p.name for p in stack.iterdir() if p.name.startswith(".")]


def test_output_paths_that_cannot_be_written_are_refused_with_their_name(tmp_path):
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "a_dir").mkdir()
    for bad, field in ((tmp_path / "a_file" / "fig.png", None), (tmp_path / "a_dir", "--out")):
        with pytest.raises(FluoInputError) as err:
            atomic.write_bytes(bad, b"x", field=field)
        assert str(bad) in str(err.value)
    with pytest.raises(FluoInputError, match="not a folder"):
        atomic.check_writable(tmp_path / "a_file", folder=True)
    with pytest.raises(FluoInputError, match="a file where a folder"):
        atomic.check_writable(tmp_path / "a_file" / "x" / "y.json")
    atomic.check_writable(tmp_path / "new" / "deeper" / "y.json")   # creatable: fine
    assert not (tmp_path / "new").exists()                         # and nothing created
    # a fresh folder set appears with the umask's mode, not mkdtemp's 0700
    with atomic.staged_folder(tmp_path / "set") as stage:
        (stage / "a.txt").write_text("a")
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "set").stat().st_mode & 0o777 == 0o777 & ~mask


@pytest.mark.slow
def test_kill_9_of_fluo_demo_and_fluo_mesh_leaves_no_damaged_file(tmp_path):
    """The two commands of issue #21, killed at random moments while they write."""
    from PIL import Image

    from FluoTomoLib.meshing.vtu_io import read_vtu

    env = dict(os.environ, OMP_NUM_THREADS="1")
    rng = random.Random(7)
    demo = tmp_path / "demo"
    for attempt in range(3):
        p = subprocess.Popen([sys.executable, "-m", "fluoapp", "demo", "--quick", "--only",
                              "phantoms", "--out", str(demo), "--seed", str(attempt)],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(3.0, 15.0))
        p.send_signal(signal.SIGKILL)
        p.wait(30)
        png = demo / "phantoms.png"
        if png.exists():
            with Image.open(png) as im:
                im.load()
        for f in demo.glob("*.json"):
            json.loads(f.read_text())
    ph = tmp_path / "ph"
    subprocess.run([sys.executable, "-m", "fluoapp", "phantom", "cylinder-tube", "--out", str(ph),
                    "--voxel-mm", "1"], env=env, check=True, capture_output=True)
    out = tmp_path / "out.vtu"
    for attempt in range(3):
        p = subprocess.Popen([sys.executable, "-m", "fluoapp", "mesh", str(ph / "CBCTLabels.nrrd"),
                              "--out", str(out), "--size", "1", "--fast"], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(2.0, 12.0))
        p.send_signal(signal.SIGKILL)
        p.wait(30)
        if out.exists():
            assert read_vtu(out).n_elements > 0
        assert not (tmp_path / "out.vtu.tmp.vtu").exists()
        assert not [f.name for f in tmp_path.iterdir()
                    if not f.name.startswith(".") and f.name not in ("demo", "ph", "out.vtu")]
