"""Figures, meshes, calibration files and data sets written as a whole: a
``kill -9`` at any step leaves the old file or the new one, never a 0-byte or
truncated file at the final name, and the next write clears the debris
(issue #21: kill -9 of ``fluo demo`` left a 0-byte ``phantoms.png``, of
``fluo mesh`` a truncated ``out.vtu.tmp.vtu``). The kills land at named crash
points (``FLUO_CRASH_AT``, test_crash_points.py), not at random moments, so
each provably interrupts a write (issue #29)."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fluoguide import atomic
from fluoguide.errors import FluoInputError
from test_crash_points import crashed, crashed_fluo, fluo, hidden, run_to_crash

ROOT = Path(__file__).resolve().parents[2]
TREE = [str(ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")]
FILES = ("figure.png", "mesh.vtu", "calibration.json")      # in the order WRITER writes them

# A child that rewrites a figure, a mesh and a calibration file three times, each
# version complete and numbered (the figure's PNG title, the mesh's point data,
# the calibration's field), so the version at each final name tells which write
# a kill interrupted.
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
    for k in range(1, 4):
        ax.set_title(f"version {{k}}")
        atomic.save_figure(fig, out + "/figure.png", dpi=100,
                           metadata={{"Title": f"version {{k}}"}})
        write_vtu(mesh, out + "/mesh.vtu", point_data={{"k": np.full(mesh.n_nodes, float(k))}})
        write_calibration_json(out + "/calibration.json", "FluoGuide.Radiometry",
                               {{"version": k, "payload": payload}})
""")


def _check_outputs(out, n_elements, versions):
    """Every final name is absent or complete and readable, and holds ``versions[name]``
    (None: absent)."""
    from PIL import Image

    from FluoTomoLib.meshing.vtu_io import read_vtu

    png = out / "figure.png"
    assert png.exists() == (versions["figure.png"] is not None)
    if png.exists():
        with Image.open(png) as im:
            im.load()                                  # decodes every byte
            assert im.size[0] > 100
            assert im.text["Title"] == f"version {versions['figure.png']}"
    vtu = out / "mesh.vtu"
    assert vtu.exists() == (versions["mesh.vtu"] is not None)
    if vtu.exists():
        mesh = read_vtu(vtu)
        assert mesh.n_elements == n_elements
        assert len(mesh.meta["point_data"]["k"]) == mesh.n_nodes
        assert set(mesh.meta["point_data"]["k"]) == {versions["mesh.vtu"]}
    cal = out / "calibration.json"
    if cal.exists():
        doc = json.loads(cal.read_text())
        assert doc["Other"] == {"kept": True}          # the other calibrations survive
        assert doc.get("Radiometry", {}).get("version") == versions["calibration.json"]
        if "Radiometry" in doc:                         # a new version, whole
            assert len(doc["Radiometry"]["payload"]) == 20000
    visible = [p.name for p in out.iterdir() if not p.name.startswith(".")]
    assert set(visible) <= {"figure.png", "mesh.vtu", "calibration.json"}, visible


def test_kill_9_at_each_write_leaves_old_or_new_files(tmp_path):
    """Killed six times, each time with one file's new version complete in its
    temporary file and not yet renamed (crash point atomic.before_replace): the
    final names hold exactly the versions written before the kill."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "calibration.json").write_text(json.dumps({"Other": {"kept": True}}))
    code = WRITER.format(tree=TREE, out=str(out))
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

    n_el = mesh_labelmap_structured(np.ones((14, 14, 14), np.int32), np.ones(3), np.zeros(3),
                                    1.0).n_elements
    versions = dict.fromkeys(FILES)
    kills = 0
    for name, k in (("figure.png", 1), ("mesh.vtu", 1), ("calibration.json", 1),
                    ("mesh.vtu", 2), ("figure.png", 3), ("calibration.json", 3)):
        path, p = run_to_crash([sys.executable, "-c", code],
                               f"atomic.before_replace@{name}:{k}")
        assert p.stdout.splitlines()[0].strip() == "ready", p.stderr
        assert path == out / name
        kills += p.returncode == -9
        # this run wrote version k of the files before `name`, k - 1 of the others
        for i, f in enumerate(FILES):
            done = k if i < FILES.index(name) else k - 1
            if done >= 1:
                versions[f] = done
        _check_outputs(out, n_el, versions)
        assert [h for h in hidden(out) if h.startswith(f".{name}.tmp-")]
    assert kills == 6
    debris = [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert debris
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
    """Killed after its temporary file is complete but before the rename (crash
    point atomic.before_replace), and in the middle of staging a data set (its
    writer's own code: no crash point is there): the final names hold the old
    content."""
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
        if which == "file":                           # FLUO_CRASH_AT kills it
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
    assert crashed([sys.executable, "-c", code, "file"], "atomic.before_replace") == target
    r = subprocess.run([sys.executable, "-c", code, "set"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 9, r.stderr
    assert target.read_bytes() == b"old"
    tmp = [p for p in tmp_path.iterdir() if p.name.startswith(".fig.png.tmp-")]
    assert [p.name for p in tmp]
    assert tmp[0].read_bytes() == b"new" * 1000      # killed with the new content complete
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


def test_kill_9_of_fluo_demo_leaves_no_damaged_file(tmp_path):
    """fluo demo (issue #21: a 0-byte phantoms.png), killed on a fresh folder with
    its metrics complete in their temporary file, then over that run's files with
    its new figure there: every final name is absent or the old file, whole, the
    scene loads, and the next run completes and clears the debris."""
    from PIL import Image

    from fluoguide import mrml_io

    demo = tmp_path / "demo"
    args = ["demo", "--quick", "--only", "phantoms", "--out", demo]
    png, metrics = demo / "phantoms.png", demo / "metrics.json"

    def check():
        if png.exists():
            with Image.open(png) as im:
                im.load()
        for f in demo.glob("*.json"):
            json.loads(f.read_text())
        mrml_io.load_scene(demo / "scene.mrml")

    at_metrics = "atomic.before_replace@demo/metrics.json"
    assert crashed_fluo(args + ["--seed", "0"], at_metrics) == metrics
    assert png.is_file() and not metrics.exists()      # written before; complete in its temp
    check()
    old = png.read_bytes()
    assert crashed_fluo(args + ["--seed", "1"], "atomic.before_replace@demo/phantoms.png") == png
    assert png.read_bytes() == old and not metrics.exists()
    check()
    debris = hidden(demo)
    assert [h for h in debris if h.startswith(".phantoms.png.tmp-")]
    assert [h for h in debris if h.startswith(".metrics.json.tmp-")]
    fluo(args + ["--seed", "1"])
    check()
    assert hidden(demo) == [] and json.loads(metrics.read_text())


def test_kill_9_of_fluo_mesh_leaves_the_old_mesh_whole(tmp_path):
    """fluo mesh over an existing out.vtu (issue #21: a truncated out.vtu.tmp.vtu),
    killed with the new mesh complete in its temporary file."""
    from FluoTomoLib.meshing.vtu_io import read_vtu

    ph = tmp_path / "ph"
    fluo(["phantom", "cylinder-tube", "--out", ph, "--voxel-mm", "2"])
    out = tmp_path / "out.vtu"
    mesh = ["mesh", ph / "CBCTLabels.nrrd", "--out", out, "--fast", "--size"]
    fluo(mesh + ["4"])
    old, n_old = out.read_bytes(), read_vtu(out).n_elements
    assert crashed_fluo(mesh + ["3"], "atomic.before_replace@out.vtu") == out
    assert out.read_bytes() == old
    assert read_vtu(out).n_elements == n_old > 0
    assert not (tmp_path / "out.vtu.tmp.vtu").exists()
    assert not [f.name for f in tmp_path.iterdir()
                if not f.name.startswith(".") and f.name not in ("demo", "ph", "out.vtu")]
    debris = [f for f in tmp_path.iterdir() if f.name.startswith(".out.vtu.tmp-")]
    assert len(debris) == 1
    n_new = read_vtu(debris[0]).n_elements              # complete, never at the final name
    assert n_new != n_old
    fluo(mesh + ["3"])                                  # the next run: the new mesh, no debris
    assert read_vtu(out).n_elements == n_new
    assert sorted(f.name for f in tmp_path.iterdir()) == ["out.vtu", "ph"]
