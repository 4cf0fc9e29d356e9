"""A bounded fuzz run of every ``fluo`` subcommand (issue #21).

The cases come from the parser itself: every option of every subcommand gets
hostile values of its kind (NaN, inf, negative, zero, huge numbers; missing,
empty, corrupt, wrong-type, non-UTF-8 and folder-instead-of-file inputs; an
output path that is a file, or below a file), one option at a time, on top of
a valid base invocation that runs in seconds. Some options also get hostile
files made for them (a truncated NRRD, a label 65535, duplicate tetrahedra, a
damaged recording, a PNG whose header claims 20000 x 20000 pixels: the known
failures of issue #21; NIfTI and NRRD headers that lie, JSON and YAML with a key
twice, points of 1e300 mm: issue #34). Each case runs in a fresh folder as its own process,
under a wall-clock limit and a memory limit (its peak resident size sampled
every 20 ms from /proc): each command's valid base invocation as a real
``python -m fluoapp``, the hostile cases as children forked from one process
that imported the stack once (``forkserver.py``: the same exit code, stdout and
stderr, without the second or two of start-up that made most of the run's
time). A case must end as:

- exit 2 with one line ``fluo: error: ...`` (argparse: ``usage`` + one error
  line) naming what was wrong, or
- exit 0 with a correct result: ``--json`` output that is clean JSON, JSON
  files it wrote free of NaN/Infinity, and never exit 0 for a NaN or inf
  value (no option accepts one); or
- exit 1 with one line for a device or peer failure (``fluo: error:``), never
  ``fluo: internal error`` (the CLI's last resort for a bug);

and always: no traceback, no hang (``TIME_LIMIT_S``), peak memory within
``MEMORY_BUDGET_MB``, nothing half-written (a failed case creates none of its
output paths), no temporary files or staging folders left, the shared fixtures
untouched.

**Declaring a new subcommand.** Add its valid, quick base invocation to
``BASES`` (command words -> argv string; ``{out}`` is a fresh path per case,
``{name}`` a fixture of :func:`build_fixtures`). A subcommand of the parser
without one is listed as a failure ("no base invocation"), never skipped. A
command that serves until stopped goes in ``SERVES`` (it passes once it prints
its address). An option whose kind the name does not tell goes in ``KINDS``.

Run it alone for a table: ``python Testing/Python/fuzz_cli.py [--only CMD] [-j 2]``
(``--only tomo`` fuzzes every tomo subcommand, ``--only "tomo batch"`` one).
``test_fuzz_cli.py`` runs it under pytest (slow).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from forkserver import Forkserver  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PYTHONPATH = os.pathsep.join(str(ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo"))
TIME_LIMIT_S = 120.0
# hard cap (RLIMIT_DATA: heap and anonymous maps; numba/LLVM reserve address
# space they never touch, so not RLIMIT_AS) and the peak resident size a case
# may reach: the largest clean case measured about 0.6 GB (see docs/reliability.md)
MEMORY_LIMIT_MB = 3072
MEMORY_BUDGET_MB = 1536
# commands allowed more (command words -> MB), each with its reason
MEMORY_BUDGET_BY_COMMAND = {
    # the Monte Carlo comparison's FEM: 0.5 mm graded box over the stored label map,
    # excitation and emission solves for 3 optodes (measured 2.3 GB)
    ("validate", "mc-fluorescence"): 2800,
}
ENV = dict(os.environ, PYTHONPATH=PYTHONPATH, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
           OPENBLAS_NUM_THREADS="1", NUMBA_NUM_THREADS="1", VTK_LOG_LEVEL="ERROR")


# ----------------------------------------------------------------- fixtures
def _fluo(args, cwd, server=None):
    """A fixture's ``fluo ARGS``: forked from ``server`` when given (the fixtures are
    inputs, not what is tested: no start-up to pay), else a real process."""
    if server is not None:
        r = server.run(args, cwd=cwd, timeout=600)
    else:
        r = subprocess.run([sys.executable, "-m", "fluoapp", *args], cwd=cwd, env=ENV,
                           capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        raise RuntimeError(f"fixture {args} failed: {r.stderr[-2000:]}")
    return r


def _hostile_files(f, fx):
    """Corrupt inputs of each kind the commands read (the known failures of #21)."""
    import numpy as np

    sys.path[:0] = [p for p in PYTHONPATH.split(os.pathsep) if p not in sys.path]
    from FluoTomoLib.meshing.mesh import Mesh
    from FluoTomoLib.meshing.vtu_io import read_vtu, write_vtu

    from fluoguide import mrml_io

    (f / "empty.json").write_text("")
    (f / "garbage.bin").write_bytes(np.random.default_rng(1).bytes(4096))
    (f / "latin1.csv").write_bytes("1,2,3\n\xe9\xe9\xe9,4,5\n".encode("latin-1"))
    (f / "wrongtype.json").write_text('{"foo": 1}')
    (f / "list.json").write_text("[1, 2, 3]")
    (f / "nan.csv").write_text("nan,0,0\n")
    (f / "adir").mkdir(exist_ok=True)
    for k in ("empty", "garbage", "latin1", "wrongtype", "list", "nan_csv", "adir"):
        fx[k] = f / {"empty": "empty.json", "garbage": "garbage.bin", "latin1": "latin1.csv",
                     "wrongtype": "wrongtype.json", "list": "list.json", "nan_csv": "nan.csv",
                     "adir": "adir"}[k]
    # label maps: a label 65535 in 4,800 voxels (cost 3.95 GB before), a cut NRRD
    lab = np.zeros((12, 20, 20), np.uint16)
    lab[2:10, 4:16, 4:16] = 1
    lab[5:7, 8:12, 8:12] = 65535
    scene = mrml_io.new_scene()
    mrml_io.add_volume(scene, "CBCTLabels", lab, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), labelmap=True)
    mrml_io.save_scene(scene, f / "lab65535" / "scene.mrml")
    fx["label65535"] = f / "lab65535" / "CBCTLabels.nrrd"
    data = fx["labels"].read_bytes()
    (f / "truncated.nrrd").write_bytes(data[: len(data) // 2])
    fx["nrrd_truncated"] = f / "truncated.nrrd"
    # ITK's own errors and lines (issue #34 item 8): a text NRRD with a 2,000-character
    # "value" (ITK's reader crashed: SIGSEGV), a MetaImage header without its data
    # (MetaIO printed its own lines), a .mha that is text
    (f / "ascii_long.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\n"
                                        b"encoding: ascii\n\n" + b"x" * 2000)
    (f / "nodata.mha").write_text("ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\n"
                                  "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n")
    (f / "text.mha").write_text("not an image\n")
    fx.update(nrrd_ascii_long=f / "ascii_long.nrrd", mha_nodata=f / "nodata.mha",
              mha_text=f / "text.mha")
    # scenes: 3,000 transforms (scene info was quadratic: 2,000 took 59 s), a
    # FIFO as a data file (blocked forever), a storage path out of the folder
    big = mrml_io.new_scene()
    for i in range(3000):
        mrml_io.set_transform(big, f"T{i}", np.eye(4))
    fx["scene_3000"] = mrml_io.save_scene(big, f / "scene3000" / "scene.mrml")
    for name, edit in (("scene_fifo", "pipe.nrrd"), ("scene_escape", "../../CBCT.nrrd")):
        d = f / name
        shutil.copytree(fx["scene"].parent, d)
        text = (d / "scene.mrml").read_text()
        (d / "scene.mrml").write_text(text.replace('fileName="CBCT.nrrd"', f'fileName="{edit}"'))
        fx[name] = d / "scene.mrml"
    os.mkfifo(f / "scene_fifo" / "pipe.nrrd")
    # meshes: duplicate tetrahedra, unused nodes, a cut .vtu
    mesh = read_vtu(fx["mesh"])
    dup = Mesh(mesh.nodes_mm, np.vstack([mesh.elements, mesh.elements[:50]]),
               np.concatenate([mesh.element_region, mesh.element_region[:50]]))
    write_vtu(dup, f / "dup_tets.vtu")
    extra = np.vstack([mesh.nodes_mm, mesh.nodes_mm[:20] + 1000.0])
    write_vtu(Mesh(extra, mesh.elements, mesh.element_region), f / "unused_nodes.vtu")
    data = fx["mesh"].read_bytes()
    (f / "truncated.vtu").write_bytes(data[: len(data) // 2])
    fx.update(dup_tets=f / "dup_tets.vtu", unused_nodes=f / "unused_nodes.vtu",
              vtu_truncated=f / "truncated.vtu")
    # recordings: a line without its keys, a cut frame file, wild timestamps
    rec = fx["recording"]
    lines = (rec / "log.jsonl").read_text().splitlines()

    def damaged(name, edit, cut_frame=False):
        d = f / name
        shutil.copytree(rec, d)
        docs = [json.loads(x) for x in lines]
        edit(docs)
        (d / "log.jsonl").write_text("\n".join(json.dumps(x) for x in docs) + "\n")
        if cut_frame:
            p = d / docs[1]["file"]
            p.write_bytes(p.read_bytes()[:100])
        fx[name] = d

    damaged("rec_nokey", lambda docs: docs[2].pop("poses"))
    damaged("rec_cutframe", lambda docs: None, cut_frame=True)
    damaged("rec_ts1e12", lambda docs: docs[2].update(timestamp_s=1e12))
    damaged("rec_ahead", lambda docs: [d.update(timestamp_s=d["timestamp_s"] + 1e6)
                                       for d in docs[2:]])
    damaged("rec_escape", lambda docs: docs[1].update(file="../../../../etc/hostname"))
    # images: 1 x 1 pixels, and a 60-byte PNG whose header claims 20000 x 20000
    import cv2
    import zlib

    (f / "tiny").mkdir(exist_ok=True)
    for k in range(4):
        cv2.imwrite(str(f / "tiny" / f"t{k}.png"), np.full((1, 1), 128, np.uint8))
    fx["png_1x1"] = str(f / "tiny" / "*.png")
    (f / "huge").mkdir(exist_ok=True)

    def chunk(kind, body):
        return (len(body).to_bytes(4, "big") + kind + body
                + zlib.crc32(kind + body).to_bytes(4, "big"))

    ihdr = (20000).to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0])
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
           + chunk(b"IDAT", zlib.compress(b"\x00" * 1000)) + chunk(b"IEND", b""))
    for k in range(4):
        (f / "huge" / f"h{k}.png").write_bytes(png)
    fx["png_huge"] = str(f / "huge" / "*.png")


def _lying_files(f, fx):
    """Files whose header or keys lie (issue #34): read silently wrong before."""
    import gzip
    import struct

    import numpy as np
    import SimpleITK as sitk

    lab = np.zeros((10, 16, 16), np.uint8)
    lab[2:8, 3:13, 3:13] = 1
    lab[4:6, 6:10, 6:10] = 2
    # a NIfTI whose voxel size is NaN (ITK: spacing 1, exit 0), edited after SimpleITK wrote it
    img = sitk.GetImageFromArray(lab)
    sitk.WriteImage(img, str(f / "pixdim_nan.nii"))
    data = bytearray((f / "pixdim_nan.nii").read_bytes())
    struct.pack_into("<f", data, 80, float("nan"))                 # pixdim[1]
    (f / "pixdim_nan.nii").write_bytes(bytes(data))

    def nrrd(name, geometry, extra=b"", encoding="raw"):
        head = (f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 16 16 10\n{geometry}"
                f"endian: little\nencoding: {encoding}\n\n").encode()
        body = lab.tobytes() + extra
        (f / name).write_bytes(head + (gzip.compress(body) if encoding == "gzip" else body))
        return f / name

    ok = "space: left-posterior-superior\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"
    fx["nii_pixdim_nan"] = f / "pixdim_nan.nii"
    fx["nrrd_extra"] = nrrd("extra.nrrd", ok, extra=b"\x01" * 64)           # was cut silently
    fx["nrrd_extra_gz"] = nrrd("extra_gz.nrrd", ok, extra=b"\x01" * 64, encoding="gzip")
    fx["nrrd_spacing_nan"] = nrrd("spacing_nan.nrrd", "spacings: 1 nan 1\n")
    fx["nrrd_spacing_zero"] = nrrd("spacing_zero.nrrd", "spacings: 0 1 1\n")
    fx["nrrd_skew"] = nrrd("skew.nrrd", "space: left-posterior-superior\n"
                                        "space directions: (1,0,0) (0.5,1,0) (0,0,1)\n")
    # JSON and YAML with a key twice: the last one won silently
    text = Path(fx["own_optics"]).read_text().rstrip()
    (f / "optics_n_twice.json").write_text(text[:-1] + ', "n": 2.9}\n')
    fx["optics_dup"] = f / "optics_n_twice.json"
    own = Path(fx["own_labels"]).parent
    (own / "batch_dup.json").write_text(json.dumps({"methods": "HP"})[:-1] + ', "cases": '
                                        '[{"labels": "labels.nrrd", "optics": "optics.json", '
                                        '"acquisition": "acq", "labels": "other.nrrd"}]}')
    (own / "batch_dup.yaml").write_text("cases:\n  - labels: labels.nrrd\n    optics: "
                                        "optics.json\n    acquisition: acq\n"
                                        "methods: HP\nmethods: NP\n")
    fx["own_batch_dup_json"], fx["own_batch_dup_yaml"] = own / "batch_dup.json", own / "batch_dup.yaml"
    # points of 1e300 mm (the SVD overflowed: a null FRE, exit 0)
    pts = np.loadtxt(fx["moving"], delimiter=",")
    pts[2, 0] = 1e300
    np.savetxt(f / "moving_1e300.csv", pts, delimiter=",")
    fx["moving_1e300"] = f / "moving_1e300.csv"
    # a recording whose log line gives its timestamp twice
    d = f / "rec_dupkey"
    shutil.copytree(fx["recording"], d)
    lines = (d / "log.jsonl").read_text().splitlines()
    lines[2] = lines[2].rstrip()[:-1] + ', "timestamp_s": 1e6}'
    (d / "log.jsonl").write_text("\n".join(lines) + "\n")
    fx["rec_dupkey"] = d


def build_fixtures(folder, server=None, jobs=1):
    """Small valid inputs for every base invocation, and hostile files.

    With a :class:`forkserver.Forkserver` the ``fluo`` commands that make the
    inputs are forked from it, ``jobs`` independent ones at a time.
    """
    import numpy as np

    f = Path(folder)
    f.mkdir(parents=True, exist_ok=True)
    fx = {}

    def fluo(args):
        return _fluo(args, f, server)

    def tube():
        fluo(["phantom", "cylinder-tube", "--out", str(f / "phantom"), "--voxel-mm", "2"])
        fluo(["mesh", str(f / "phantom" / "CBCTLabels.nrrd"), "--out", str(f / "mesh.vtu"),
              "--size", "3", "--fast"])

    # the commands whose outputs are inputs (independent of one another but for
    # the tube's mesh), then the files made from them
    steps = [tube,
             lambda: fluo(["calib", "synth-boards", "--out", str(f / "boards"), "--views", "4",
                           "--width", "320", "--height", "240"]),
             lambda: fluo(["calib", "synth-light", "--out", str(f / "light")]),
             lambda: fluo(["nav", "synth", "--out", str(f / "nav"), "--views", "1", "--binning",
                           "8", "--triangles", "5000"]),
             lambda: fluo(["record", "--out", str(f / "rec"), "--seconds", "0.6", "--fps", "5",
                           "--width", "64", "--height", "48"]),
             lambda: _own_scene(f, fx, server)]
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        for fut in [pool.submit(step) for step in steps]:
            fut.result()
    fx["scene"] = f / "phantom" / "scene.mrml"
    fx["labels"] = f / "phantom" / "CBCTLabels.nrrd"
    fx["mesh"] = f / "mesh.vtu"
    np.savetxt(f / "sources.csv", [[0.0, 0.0, 0.0]], delimiter=",")
    np.savetxt(f / "detectors.csv", [[5.0, 0.0, 0.0], [10.0, 0.0, 0.0]], delimiter=",")
    fx["sources"], fx["detectors"] = f / "sources.csv", f / "detectors.csv"
    fx["images"] = str(f / "boards" / "*.png")
    fx["board_truth"] = f / "boards" / "truth.json"
    fx["stack"] = f / "light" / "stack"
    fx["illumination"] = f / "light" / "illumination"
    fx["laser"] = f / "light" / "laser"
    rng = np.random.default_rng(0)
    pts = rng.uniform(-50, 50, (6, 3))
    np.savetxt(f / "moving.csv", pts, delimiter=",")
    np.savetxt(f / "fixed.csv", pts + [1.0, 2.0, 3.0], delimiter=",")
    fx["moving"], fx["fixed"] = f / "moving.csv", f / "fixed.csv"
    poses = []
    for k in range(8):
        a = 0.3 * np.array([np.cos(k), np.sin(k), 0.5])
        th = np.linalg.norm(a)
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]) / th
        R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [100, 50, 20] - R @ [0, 0, 150]
        poses.append(T.tolist())
    (f / "pivot.json").write_text(json.dumps({"tool_to_tracker": poses}))
    fx["pivot"] = f / "pivot.json"
    mc_data = ROOT / "FluoTomo" / "FluoTomoLib" / "montecarlo" / "data"
    fx["mc_halfspace"] = mc_data / "halfspace_n137.json"
    fx["mc_fluorescence"] = mc_data / "fluorescence_inclusion.json"
    fx["nav_scene"] = f / "nav" / "scene.mrml"
    fx["recording"] = f / "rec"
    _dicom_series(f, fx)
    _hostile_files(f, fx)
    _lying_files(f, fx)
    fx["root"] = f
    return fx


def _dicom_series(f, fx):
    """A small CBCT as a DICOM series (oblique, slope 2, intercept -1024: -24..652 HU)."""
    import dicom_cases as dc

    uid = "1.2.826.0.1.3680043.2.1125.77.1"
    dc.write_series(f / "dicom", dc.test_volume((8, 12, 14)) + 1000, (0.5, 0.6, 0.8),
                    (10.0, 20.0, 30.0), dc.rotation(20.0, -25.0, 10.0), slope=2.0,
                    intercept=-1024.0, uid=uid)
    fx.update(cbct_dicom=f / "dicom", cbct_series=uid)


def _own_scene(f, fx, server=None):
    """fluo tomo's inputs: a small label map unlike the tube (labels 3 and 7, an
    inclusion under a curved top, direction diag(-1, -1, 1)), its optics.json and
    an acquisition simulated from it (the default scan, 'fast')."""
    sys.path[:0] = [p for p in PYTHONPATH.split(os.pathsep) if p not in sys.path]
    from fluoguide.labelmap_io import write_volume_nrrd
    from fluoguide.phantoms import ellipsoid_inclusion_labelmap, ellipsoid_inclusion_optics

    d = f / "own"
    d.mkdir(exist_ok=True)
    sc = ellipsoid_inclusion_labelmap(semi_axes_mm=(12.0, 10.0, 7.0), spacing_mm=(1.0, 1.0, 1.0),
                                      inclusion_diameter_mm=4.0, inclusion_gap_mm=2.0,
                                      inclusion_offset_mm=(0.0, 0.0))
    write_volume_nrrd(d / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"], sc["origin_mm"],
                      sc["direction"])
    optics = ellipsoid_inclusion_optics()
    (d / "optics.json").write_text(json.dumps(optics))
    _fluo(["tomo", "simulate", "--labels", str(d / "labels.nrrd"), "--optics",
           str(d / "optics.json"), "--yield", "7:0.0026", "--accuracy", "fast", "--out",
           str(d / "acq")], f, server)
    fx.update(own_labels=d / "labels.nrrd", own_optics=d / "optics.json", own_acq=d / "acq")
    # fluo tomo acquire: a recording rendered from the same scene (docs/recording.md)
    _fluo(["tomo", "record-scan", "--labels", str(d / "labels.nrrd"), "--optics",
           str(d / "optics.json"), "--yield", "7:0.0026", "--seed", "1", "--out",
           str(d / "rec")], f, server)
    fx["own_recording"] = d / "rec"
    # fluo tomo batch: one case (HP) on those inputs, and batch files that must be refused
    head = "name,labels,optics,acquisition,methods,truth\n"
    for name, row in (("batch", "own,labels.nrrd,optics.json,acq,HP,0.0026"),
                      ("batch_escape", "own,../../../etc/passwd,optics.json,acq,HP,"),
                      ("batch_nan_truth", "own,labels.nrrd,optics.json,acq,HP,nan"),
                      ("batch_dup", "own,labels.nrrd,optics.json,acq,HP,\n"
                                    "own,labels.nrrd,optics.json,acq,SP,")):
        (d / f"{name}.csv").write_text(head + row + "\n")
        fx[f"own_{name}"] = d / f"{name}.csv"


# ----------------------------------------------------------------- declarations
# Command words -> a valid invocation that runs in seconds (the fuzz changes one
# option at a time). {out} is a fresh path per case, {name} a fixture.
BASES = {
    ("phantom",): "phantom cylinder-tube --out {out} --voxel-mm 2 --seed 0 --depth-mm 4.7",
    ("scene", "info"): "scene info {scene}",
    ("scene", "import"): "scene import --cbct {cbct_dicom} --series {cbct_series} --out {out}",
    ("segment",): "segment --cbct {cbct_dicom} --thresholds 1:-500:3000,2:300:3000 "
                  "--out {out}.nrrd",
    ("demo",): "demo --out {out} --quick --only phantoms",
    ("app",): "app --port 0 --workspace {out} --scene {scene}",
    ("analytic",): "analytic --mua 0.01 --musp 1 --n 1.37 --rho 3,10 --yield 0.001 --mua-m 0.007 "
                   "--musp-m 0.8",
    ("forward",): "forward --mesh {mesh} --mua 0.01 --musp 1 --n 1.37 --sources {sources} "
                  "--detectors {detectors} --jacobian --jacobian-out {out}.npy",
    ("study",): "study A --target 6,3.5 --out {out}",
    ("mesh",): "mesh {labels} --out {out}.vtu --size 3 --fast",
    ("calib", "camera"): "calib camera --images {images} --board chessboard:9x6:20 --yaml {out}.yaml",
    ("calib", "handeye"): "calib handeye --images {images} --board chessboard:9x6:20 "
                          "--poses {board_truth} --method TSAI",
    ("calib", "register"): "calib register --moving {moving} --fixed {fixed}",
    ("calib", "pivot"): "calib pivot --poses {pivot}",
    ("calib", "synth-boards"): "calib synth-boards --out {out} --views 2 --width 160 --height 120 "
                               "--noise 1 --blur 0.5 --tracker-noise-mm 0.1",
    ("calib", "radiometry"): "calib radiometry {stack} --bits 14 --out {out} "
                             "--calibration {out}.json",
    ("calib", "illumination"): "calib illumination {illumination} --axisymmetric --out {out} "
                               "--calibration {out}.json",
    ("calib", "laser"): "calib laser {laser} --calibration {out}.json",
    ("calib", "synth-light"): "calib synth-light --out {out} --seed 1",
    ("devices",): "devices",
    ("track",): "track --sim --seconds 0.5 --seed 0",
    ("record",): "record --out {out} --seconds 0.5 --fps 5 --width 64 --height 48 --seed 0",
    ("replay",): "replay {recording}",
    ("nav", "synth"): "nav synth --out {out} --views 1 --binning 8 --triangles 5000 --transport 0.3",
    ("nav", "correct"): "nav correct --scene {nav_scene} --frame 0 --out {out}",
    ("bench", "mapping"): "bench mapping --repeats 1 --binning 16",
    # the stored Monte Carlo sets (no Monte Carlo run: seconds, not minutes)
    # a small label map (own scene fixture): simulate meshes it whole at 'fast'
    ("tomo", "simulate"): "tomo simulate --labels {own_labels} --optics {own_optics} "
                          "--yield 7:0.0026 --accuracy fast --seed 1 --out {out}",
    ("tomo", "plan"): "tomo plan --labels {own_labels} --optics {own_optics} --target 7 "
                      "--positions 6 --time-budget-s 2 --out {out}",
    ("tomo", "reconstruct"): "tomo reconstruct --labels {own_labels} --optics {own_optics} "
                             "--acquisition {own_acq} --accuracy fast --method HP --out {out}",
    ("tomo", "batch"): "tomo batch {own_batch} --accuracy fast --out {out}",
    ("tomo", "acquire"): "tomo acquire --recording {own_recording} --labels {own_labels} "
                         "--optics {own_optics} --out {out}",
    ("tomo", "record-scan"): "tomo record-scan --labels {own_labels} --optics {own_optics} "
                             "--yield 7:0.0026 --seed 1 --out {out}",
    ("validate", "mc"): "validate mc --mc-in {mc_halfspace} --mesh-level test --boundary fresnel "
                        "--out {out}",
    ("validate", "mc-fluorescence"): "validate mc-fluorescence --mc-in {mc_fluorescence} "
                                     "--boundary fresnel --out {out}",
    # the stored Monte Carlo and diffusion data, HP on the graded mesh (seconds)
    ("validate", "mc-tomography"): "validate mc-tomography --depths 4.7 --methods HP "
                                   "--out {out}",
}

# Commands whose valid invocation serves until stopped: the case passes when
# stdout shows this line (then the process is stopped).
SERVES = {("app",): "FluoGuide app: http"}

# Commands whose valid invocation takes minutes by its nature (command words ->
# why): the base is not run (a slow test runs it), and every hostile case must
# be refused before any work (exit 2 inside the time limit), a stricter test.
REFUSE_ONLY = {}     # none now: validate mc-tomography's base reads stored data (seconds)

# Option kinds the name does not tell (option string or positional dest -> kind).
KINDS = {"--board": "str", "--roi": "str", "--refine": "str", "--rho": "str", "--target": "str",
         "--igtl": "str", "--serial": "str", "--host": "str", "--method": "str",
         "--store-method": "str", "--only": "str", "--solver": "str", "--motion": "str",
         "--allow-origin": "str", "--workspace": "outdir", "--frames": "indir",
         "name": "str", "study": "str", "--sweep": "str", "--scheme": "str", "--hp-basis": "str",
         "--labels": "inpath", "--optics": "inpath", "--acquisition": "indir",
         "--yield": "str", "--engine": "str", "--accuracy": "str", "--data-model": "str",
         "batch": "inpath", "--methods": "str", "--cbct": "inpath", "--series": "str",
         "--thresholds": "str", "--recording": "indir", "--calibration": "inpath",
         "--scene": "inpath", "--missing-pose": "str", "--saturated-frames": "str",
         "--spot-off": "str"}

HOSTILE = {
    "float": ["nan", "inf", "-inf", "-1", "0", "1e300"],
    "int": ["-1", "0", "1000000000"],
    "inpath": ["{missing}", "{empty}", "{garbage}", "{adir}", "{latin1}", "{wrongtype}", "{list}"],
    "indir": ["{missing}", "{empty}", "{adir}"],
    "glob": ["{missing}/*.png", "{garbage}", "/etc/*", "{png_1x1}", "{png_huge}"],
    "outpath": ["{a_file}/sub", "{a_file}", "{a_dir}"],
    "outdir": ["{a_file}/sub", "{a_file}"],
    "str": ["", "garbage,,1e999", "nan"],
}

# Numbers no option accepts: a run given one must refuse it (exit 2), not
# compute with it (the exit-0-on-garbage of issue #21), unless listed in ACCEPTS.
MUST_REFUSE = {"nan", "inf", "-inf", "-1", "1e300", "1000000000"}
# (option, value) -> why the value is legitimate after all
ACCEPTS = {("--seed", "1000000000"): "seeds are 0..2**32-1"}
# More values one option must refuse (command words, option) -> values: the
# exit-0-on-garbage cases of issue #21 that the generic values miss.
REFUSE_ALSO = {
    (("nav", "synth"), "--views"): ["0"],
    (("nav", "synth"), "--binning"): ["0"],
    (("calib", "radiometry"), "--bits"): ["1000"],
    (("demo",), "--only"): ["bogus"],
    (("mesh",), "--refine"): ["sphere:0,0,0,5,1"],      # the base uses --fast: not applied
    (("track",), "--tools"): ["3"],                      # --sim: not applied
    # batch files naming a path outside their folder, a NaN truth, one name twice
    (("tomo", "batch"), "batch"): ["{own_batch_escape}", "{own_batch_nan_truth}",
                                   "{own_batch_dup}", "{own_batch_dup_json}",
                                   "{own_batch_dup_yaml}"],
    # issue #34: files that lie (a NaN voxel size was meshed, extra NRRD data cut
    # off, a key given twice read as its last value) and values that passed
    (("mesh",), "labelmap"): ["{nii_pixdim_nan}", "{nrrd_extra}", "{nrrd_extra_gz}",
                              "{nrrd_spacing_nan}", "{nrrd_spacing_zero}", "{nrrd_skew}"],
    (("tomo", "simulate"), "--labels"): ["{nii_pixdim_nan}", "{nrrd_extra}",
                                         "{nrrd_spacing_nan}"],
    (("tomo", "simulate"), "--optics"): ["{optics_dup}"],
    (("tomo", "reconstruct"), "--labels"): ["{nrrd_extra_gz}"],
    (("forward",), "--solver"): ["bogus"],
    (("analytic",), "--rho"): ["1e300", "3,1e5"],
    (("calib", "register"), "--moving"): ["{moving_1e300}"],
    (("replay",), "folder"): ["{rec_dupkey}"],
}

# Whole invocations of issue #21 that need another base: (command words, what,
# argv, must be refused).
SPECIAL = [
    (("mesh",), "--threads -3 (quality mesher: fTetWild spun)",
     "mesh {labels} --out {out}.vtu --size 6 --threads -3", True),
    (("mesh",), "--threads 1 (quality mesher)", "mesh {labels} --out {out}.vtu --size 6 "
     "--threads 1", False),
    # issue #34: inside the documented 0.1..5 mm, 13.7 GB: refused before it starts
    # under the case's 3 GB cap (it ran out of memory: exit 1)
    (("phantom",), "--voxel-mm 0.1 (13.7 GB)", "phantom cylinder-tube --out {out} "
     "--voxel-mm 0.1", True),
]

# Hostile files made for one option (command words, option) -> fixture names.
EXTRA = {
    (("mesh",), "labelmap"): ["{label65535}", "{nrrd_truncated}", "{nrrd_ascii_long}",
                              "{mha_nodata}", "{mha_text}"],
    (("tomo", "simulate"), "--labels"): ["{nrrd_ascii_long}", "{mha_nodata}"],
    (("scene", "info"), "scene"): ["{scene_3000}", "{scene_fifo}", "{scene_escape}"],
    (("forward",), "--mesh"): ["{dup_tets}", "{unused_nodes}", "{vtu_truncated}"],
    (("forward",), "--sources"): ["{nan_csv}"],
    (("calib", "register"), "--moving"): ["{nan_csv}"],
    (("replay",), "folder"): ["{rec_nokey}", "{rec_cutframe}", "{rec_ts1e12}", "{rec_ahead}",
                              "{rec_escape}"],
}


def _kind(action):
    """The hostile-value kind of an argparse action."""
    name = action.option_strings[-1] if action.option_strings else action.dest
    if name in KINDS:
        return name, KINDS[name]
    if action.type is int:
        return name, "int"
    if action.type is float:
        return name, "float"
    bare = name.lstrip("-")
    if bare == "images":
        return name, "glob"
    if "out" in bare or "yaml" in bare or bare == "calibration":
        return name, "outpath"
    if bare in ("folder", "stack") or "folder" in bare:
        return name, "inpath"
    return name, "inpath" if any(w in bare for w in (
        "scene", "mesh", "sources", "detectors", "poses", "moving", "fixed", "labelmap",
        "intrinsics", "targets", "board-to")) else "str"


def command_options():
    """Command words -> [(option string or positional dest, kind, takes a value)]."""
    from fluoapp.cli import build_parser

    out = {}

    def walk(parser, path):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subs:
            for name, sp in subs[0].choices.items():
                walk(sp, path + (name,))
            return
        opts = []
        for a in parser._actions:
            if isinstance(a, argparse._HelpAction) or a.nargs == 0:
                continue
            opts.append(_kind(a))
        out[path] = (parser, opts)

    walk(build_parser(), ())
    return out


def missing_bases():
    """Subcommands of the parser without a base invocation (listed, never skipped)."""
    return sorted(" ".join(p) for p in command_options() if p not in BASES)


@dataclass
class Case:
    command: tuple
    option: str
    value: str
    argv: list | None
    result: dict = field(default_factory=dict)
    must_refuse: bool = False


def _positional_index(parser, argv, ncmd, dest):
    """Index in ``argv`` of the positional ``dest`` (options skipped with their values)."""
    positionals = [a.dest for a in parser._actions if not a.option_strings]
    takes = {s: a.nargs != 0 for a in parser._actions for s in a.option_strings}
    k, i = 0, ncmd
    while i < len(argv):
        tok = argv[i]
        if tok.startswith("-") and tok in takes:
            i += 2 if takes[tok] else 1
            continue
        if k < len(positionals) and positionals[k] == dest:
            return i
        k += 1
        i += 1
    return None


def make_cases(only=None):
    cases = []
    for path, (parser, opts) in sorted(command_options().items()):
        # "tomo" fuzzes every tomo subcommand, "tomo batch" that one
        if only and not any((" ".join(path) + " ").startswith(o.strip() + " ") for o in only):
            continue
        base = BASES.get(path)
        if base is None:
            cases.append(Case(path, "-", "-", None, {"ok": False, "why": "no base invocation: "
                                                     "declare one in fuzz_cli.BASES"}))
            continue
        base = shlex.split(base)
        json_flag = ["--json"] if any("--json" in a.option_strings for a in parser._actions) else []
        refuse_only = path in REFUSE_ONLY
        if not refuse_only:
            cases.append(Case(path, "(base)", "-", base + json_flag))
        for opt, kind in opts:
            refuse = [v for v in HOSTILE[kind] if kind in ("int", "float") and v in MUST_REFUSE
                      and (opt, v) not in ACCEPTS] + REFUSE_ALSO.get((path, opt), [])
            for value in HOSTILE[kind] + EXTRA.get((path, opt), []) + REFUSE_ALSO.get((path, opt), []):
                argv = list(base)
                if opt.startswith("-"):
                    if opt in argv:
                        argv[argv.index(opt) + 1] = value
                    else:
                        argv += [opt, value]
                else:
                    i = _positional_index(parser, argv, len(path), opt)
                    if i is None:
                        continue
                    argv[i] = value
                cases.append(Case(path, opt, value, argv + json_flag,
                                  must_refuse=refuse_only or value in refuse))
    for path, what, argv, refuse in SPECIAL:
        if not only or any((" ".join(path) + " ").startswith(o.strip() + " ") for o in only):
            cases.append(Case(path, what, "-", shlex.split(argv) + ["--json"], must_refuse=refuse))
    return cases


# ----------------------------------------------------------------- running
def _snapshot(folder):
    return {p.relative_to(folder) for p in Path(folder).rglob("*")}


def _tree(folder):
    """Every path below ``folder`` (relative, as text): the same set as
    :func:`_snapshot`, listed by ``os.walk`` (the shared fixtures hold 3,000
    files and are listed twice a case)."""
    out = set()
    for top, dirs, files in os.walk(folder):
        rel = os.path.relpath(top, folder)
        for name in dirs + files:
            out.add(name if rel == "." else os.path.join(rel, name))
    return out


def _debris(paths):
    return [str(x) for x in paths if ".tmp-" in x.name or ".stage-" in x.name
            or x.name.startswith(".fluo-stage") or x.name.endswith(".tmp")]


def _json_files_with_nan(folder):
    bad = []
    for p in Path(folder).rglob("*.json"):
        try:
            json.loads(p.read_text(), parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
        except (ValueError, UnicodeDecodeError, OSError):
            bad.append(p.name)
    return bad


def _hwm_kb(pid):
    """The process image's peak resident size [kB] (VmHWM; reset at exec, unlike
    ru_maxrss, which keeps the forking parent's size)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def _wait(p, deadline, serve_marker=None, stdout_path=None):
    """Wait for ``p``, sampling its peak memory; returns (peak kB, hung, served)."""
    peak = 0
    while True:
        peak = max(peak, _hwm_kb(p.pid))
        pid, status, _ = os.wait4(p.pid, os.WNOHANG)
        if pid == p.pid:
            p.returncode = os.waitstatus_to_exitcode(status)
            return peak, False, False
        served = (serve_marker is not None and stdout_path.exists()
                  and serve_marker in stdout_path.read_text(errors="replace"))
        if served or time.monotonic() > deadline:
            os.killpg(p.pid, signal.SIGTERM if served else signal.SIGKILL)
            t_kill = time.monotonic()
            while True:
                pid, status, _ = os.wait4(p.pid, os.WNOHANG)
                if pid == p.pid:
                    p.returncode = os.waitstatus_to_exitcode(status)
                    return peak, not served, served
                if time.monotonic() - t_kill > 10:
                    os.killpg(p.pid, signal.SIGKILL)
                time.sleep(0.05)
        time.sleep(0.02)


def _run_process(argv, cwd, logs, serve):
    """``python -m fluoapp ARGV`` as its own process, limits as for a forked case."""
    t0 = time.monotonic()
    with open(logs / "stdout", "wb") as so, open(logs / "stderr", "wb") as se:
        p = subprocess.Popen([sys.executable, "-m", "fluoapp", *argv], cwd=cwd, env=ENV,
                             stdout=so, stderr=se, stdin=subprocess.DEVNULL,
                             start_new_session=True)
        lim = MEMORY_LIMIT_MB * 2**20
        try:
            resource.prlimit(p.pid, resource.RLIMIT_DATA, (lim, lim))
        except (OSError, ValueError):
            pass
        peak_kb, hung, served = _wait(p, t0 + TIME_LIMIT_S, serve, logs / "stdout")
    seconds = time.monotonic() - t0
    out = (logs / "stdout").read_text(errors="replace")
    err = (logs / "stderr").read_text(errors="replace")
    return p.returncode, peak_kb, hung, served, seconds, out, err


# a progress line (fluoguide.progress): "calib camera:  20% detecting board 2/4 (3 s)"
PROGRESS = re.compile(r"^[\w .-]+: +\d+% .*\(\d+ s\)$")


def run_case(case, fx, work, server=None):
    """Run one case in a fresh folder and judge it; fills ``case.result``.

    With a :class:`forkserver.Forkserver` the hostile cases run as children
    forked from it (the same exit code, stdout and stderr, without a second of
    start-up each); a command's valid base invocation always runs as a real
    ``python -m fluoapp`` process.
    """
    cwd = Path(tempfile.mkdtemp(prefix="case-", dir=work))
    logs = Path(tempfile.mkdtemp(prefix="log-", dir=work))
    (cwd / "a_file").write_text("a file where a folder is expected\n")
    (cwd / "a_dir").mkdir()
    subst = {k: str(v) for k, v in fx.items()}
    subst.update(missing=str(cwd / "does-not-exist"), a_file=str(cwd / "a_file"),
                 a_dir=str(cwd / "a_dir"), out=str(cwd / "out"))
    argv = [a.format(**subst) for a in case.argv]
    before_fx = _tree(fx["root"])
    before = _snapshot(cwd)
    serve = SERVES.get(case.command)
    if server is None or case.option == "(base)":
        # the valid invocation of each command: a real ``python -m fluoapp`` process
        rc, peak_kb, hung, served, seconds, out, err = _run_process(argv, cwd, logs, serve)
    else:
        res = server.run(argv, cwd=cwd, timeout=TIME_LIMIT_S, memory_limit_mb=MEMORY_LIMIT_MB,
                         serve_marker=serve)
        rc, peak_kb, hung, served = res.returncode, res.peak_mb * 1024, res.hung, res.served
        seconds, out, err = res.seconds, res.stdout, res.stderr
    peak_mb = peak_kb / 1024.0
    r = {"argv": argv, "rc": rc, "seconds": round(seconds, 2),
         "peak_mb": round(peak_mb), "stderr": err[-600:]}
    problems = []
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if hung:
        problems.append(f"hung (> {TIME_LIMIT_S:.0f} s)")
    elif "Traceback (most recent call last)" in err:
        problems.append("traceback")
    elif served:
        if case.must_refuse:
            problems.append(f"served with {case.value} (must be refused)")
    elif case.option == "(base)" and rc != 0:
        problems.append(f"the base invocation failed (exit {rc}): the fuzz of this "
                        "command tests nothing")
    elif rc == 2:
        if not lines or not (lines[-1].startswith("fluo: error:") or
                             (lines[-1].startswith("fluo ") and ": error:" in lines[-1])):
            problems.append("exit 2 without a 'fluo: error:' line")
        elif sum(": error:" in ln for ln in lines) > 1:
            problems.append("more than one error line")
        elif lines[-1].startswith("fluo: error:") and not all(map(PROGRESS.match, lines[:-1])):
            # a library's own lines or a Python warning before the error (issue #34)
            other = next(ln for ln in lines[:-1] if not PROGRESS.match(ln))
            problems.append(f"a line before the error that is not progress: {other[:80]!r}")
    elif rc == 1:
        if "internal error" in err or not lines or not lines[-1].startswith("fluo: error:"):
            problems.append("exit 1: unexpected exception")
    elif rc == 0:
        if case.must_refuse:
            problems.append(f"exit 0 on {case.value} (must be refused)")
        if "--json" in argv:
            try:
                json.loads(out, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
            except ValueError as exc:
                problems.append(f"stdout is not clean JSON ({str(exc)[:60]})")
        nan_files = _json_files_with_nan(cwd)
        if nan_files:
            problems.append(f"wrote JSON with NaN/Infinity: {nan_files[:3]}")
    elif rc is not None and rc < 0:
        problems.append(f"killed by signal {-rc}")
    else:
        problems.append(f"exit {rc}")
    budget_mb = MEMORY_BUDGET_BY_COMMAND.get(tuple(case.command), MEMORY_BUDGET_MB)
    if peak_mb > budget_mb:
        problems.append(f"peak memory {peak_mb:.0f} MB > {budget_mb} MB")
    after = _snapshot(cwd)
    debris = _debris(after)
    if debris:
        problems.append(f"temporary files left: {debris[:3]}")
    if rc != 0 and not served:
        new = sorted(str(x) for x in after - before if x.parts[0].startswith("out"))
        if new:
            problems.append(f"failed but wrote {new[:3]}")
    if _tree(fx["root"]) != before_fx:
        problems.append("changed the shared fixtures")
    r["ok"] = not problems
    r["why"] = "; ".join(problems)
    case.result = r
    shutil.rmtree(logs, ignore_errors=True)
    if r["ok"]:
        shutil.rmtree(cwd, ignore_errors=True)
    return case


def run(only=None, jobs=2, work=None, progress=None):
    """Build the fixtures, run every case (``jobs`` at a time); returns the cases."""
    work = Path(work or tempfile.mkdtemp(prefix="fluo-fuzz-"))
    work.mkdir(parents=True, exist_ok=True)
    cases = make_cases(only)
    todo = [c for c in cases if c.argv is not None]

    # the cases running at once share jobs x MEMORY_BUDGET_MB (each counts its
    # command's budget): with two jobs, two ordinary cases side by side and a
    # 2.8 GB one alone, so the whole run stays a light test of the suite
    # (conftest.py: under 4 GB)
    total_mb = jobs * MEMORY_BUDGET_MB
    room = {"mb": total_mb}
    cond = threading.Condition()

    def one(c):
        need = min(total_mb, MEMORY_BUDGET_BY_COMMAND.get(tuple(c.command), MEMORY_BUDGET_MB))
        with cond:
            cond.wait_for(lambda: room["mb"] >= need)
            room["mb"] -= need
        try:
            run_case(c, fx, work, server)
        finally:
            with cond:
                room["mb"] += need
                cond.notify_all()
        if progress:
            progress(c)
        return c

    # one process imports the stack; each hostile case is a child forked from it
    # (and so is each command that makes the fixtures)
    with Forkserver(env=ENV) as server:
        fx = build_fixtures(work / "fixtures", server, jobs)
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            list(pool.map(one, todo))
    return cases


def summary(cases):
    rows = {}
    for c in cases:
        key = " ".join(c.command)
        ok, n, s = rows.get(key, (0, 0, 0.0))
        rows[key] = (ok + bool(c.result.get("ok")), n + 1, s + c.result.get("seconds", 0.0))
    return rows


def describe(c):
    return (f"{' '.join(c.command)} {c.option}={c.value!r}: {c.result.get('why')} "
            f"(rc {c.result.get('rc')}, {c.result.get('seconds')} s) "
            f"{c.result.get('stderr', '')[-300:]!r}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="*", help="first words of the commands to fuzz")
    ap.add_argument("-j", "--jobs", type=int, default=2, help="cases run at once (default 2)")
    ap.add_argument("--work", help="folder for fixtures and failed cases (default: a temp folder)")
    ap.add_argument("--json", help="write every case's result to this JSON file")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    cases = run(args.only, args.jobs, args.work,
                progress=lambda c: None if c.result.get("ok") else print("FAIL", describe(c),
                                                                          flush=True))
    wall = time.monotonic() - t0
    bad = [c for c in cases if not c.result.get("ok")]
    for key, (ok, n, s) in sorted(summary(cases).items()):
        print(f"{key:24s} {ok:4d} / {n:4d} clean  {s:7.1f} s")
    peak = max((c.result.get("peak_mb", 0) for c in cases), default=0)
    print(f"\n{len(cases) - len(bad)} of {len(cases)} cases clean "
          f"({100.0 * (len(cases) - len(bad)) / max(1, len(cases)):.1f} %) in {wall:.0f} s "
          f"wall, {args.jobs} at a time; largest peak memory {peak} MB")
    for c in bad:
        print("-", describe(c))
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"wall_s": wall, "jobs": args.jobs,
             "cases": [{"command": c.command, "option": c.option, "value": c.value, **c.result}
                       for c in cases]}, indent=1))
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
