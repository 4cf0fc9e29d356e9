"""The surface-mapping kernels made ready before long work (issue #33: long work
reports at least every 2 s): ``FluoNavLib.mapping.kernels.prepare_kernels``
compiles (or loads) every numba kernel the ray cast and the illumination model
call, reporting as it goes, for exactly the argument types of their call sites,
so a cast after it compiles nothing (a first cast used to compile silently for
14-16 s inside whatever step came first).

Each check runs in a fresh process: there the kernels hold no signature but the
ones ``prepare_kernels`` compiled, and a call with any other one cannot hide
behind a signature another test compiled earlier."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

COMPILING = "compiling the surface-mapping kernels (first run only)"
LOADING = "loading the compiled surface-mapping kernels"

# ``logic``: the kernels are made ready by FluoNavLogic's frame job (its first
# step), else by prepare_kernels itself. Then every kernel is frozen (a call with
# a signature it does not hold raises TypeError instead of compiling) and a
# surface from VTK is cast with a distorted camera (pixel-space raster) and an
# undistorted one (exact grid), full and binned, and lit by an asymmetric cone
# coupled to the camera and by a tracked axisymmetric one.
PROBE = """
import json, sys, time
from FluoNavLib.mapping import kernels

reports, out = [], {}
def progress(fraction, message):
    reports.append((time.monotonic(), message))

dispatchers = [d for d, _ in kernels._examples()]
if sys.argv[1] == "logic":
    from fluoguide import mrml_io
    from FluoNav import FluoNavLogic

    logic = FluoNavLogic(mrml_io.new_scene())
    logic.makeSyntheticAcquisition(views=1, binning=8, triangles=4000)
    out["missing_before"] = len(kernels.missing())
    out["start"] = time.monotonic()
    out["mapped"] = int(logic.correctFrame(0, progress=progress).mapped.sum())
elif sys.argv[1] in ("cast", "log"):
    # no preparation: a script's own first cast, with a reporter ("cast") or with
    # none, where the logger says it ("log")
    import logging
    import numpy as np
    from FluoCalibLib.geometry import transforms as tf
    from FluoCalibLib.geometry.camera_model import CameraModel
    from FluoNavLib.mapping.pixel_cast import SurfaceCaster, cast_camera

    class Keep(logging.Handler):
        def emit(self, record):
            reports.append((time.monotonic(), record.getMessage()))

    logging.getLogger("fluoguide.kernels").addHandler(Keep())
    logging.getLogger("fluoguide.kernels").setLevel(logging.INFO)
    plane = SurfaceCaster(np.array([[-50.0, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]]),
                          np.array([[0, 1, 2], [0, 2, 3]]))
    out["missing_before"] = len(kernels.missing())
    out["start"] = time.monotonic()
    hits = cast_camera(plane, CameraModel(300.0, 300.0, 79.5, 59.5, (0.0,) * 5, 160, 120),
                       tf.look_at([0.0, 0.0, 100.0], [0.0, 0.0, 0.0], up=(0, 1, 0)),
                       progress=progress if sys.argv[1] == "cast" else None)
    out["plane_seen"] = int(hits.visible.sum())
else:
    out["missing_before"] = len(kernels.missing())
    out["start"] = time.monotonic()
    kernels.prepare_kernels(progress)
out["end"] = time.monotonic()
out["missing_after"] = len(kernels.missing())
out["overloads_prepared"] = {d.__name__: len(d.overloads) for d in dispatchers}

import vtk
from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.radiometry.illumination_model import IlluminationCone
from FluoNavLib.mapping.flux_map import view_model
from FluoNavLib.mapping.pixel_cast import SurfaceCaster, cast_camera

for d in dispatchers:
    d.disable_compile()
sphere = vtk.vtkSphereSource()
sphere.SetRadius(50.0)
sphere.SetThetaResolution(24)
sphere.SetPhiResolution(24)
triangles = vtk.vtkTriangleFilter()
triangles.SetInputConnection(sphere.GetOutputPort())
triangles.Update()
caster = SurfaceCaster.from_polydata(triangles.GetOutput())
pose = tf.look_at([0.0, 10.0, 120.0], [0.0, 0.0, 0.0], up=(0, 1, 0))
light = tf.look_at([20.0, 0.0, 120.0], [0.0, 0.0, 0.0], up=(0, 1, 0))
coupled = IlluminationCone(half_angle_deg=60.0, alpha=2.0, gamma_per_mm=0.01,
                           asym_amplitude=0.2)
tracked = IlluminationCone(half_angle_deg=40.0, alpha=0.0)
out["lit"] = 0
for dist in ((-0.1, 0.02, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0)):
    cam = CameraModel(300.0, 300.0, 79.5, 59.5, dist, 160, 120)
    for binning in (1, 4):
        hits = cast_camera(caster, cam, pose, binning=binning)
        out["lit"] += int(view_model(hits, coupled, pose).lit.sum())
        out["lit"] += int(view_model(hits, tracked, pose, light_to_world=light).lit.sum())
out["overloads_after"] = {d.__name__: len(d.overloads) for d in dispatchers}
out["reports"] = reports
print(json.dumps(out))
"""


def _probe(mode, cache_dir=None):
    """The probe's findings in a fresh process (numba's cache in ``cache_dir``, else
    the test run's)."""
    env = dict(os.environ)
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    r = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _check_nothing_compiled_after(out):
    """Every kernel holds the one signature prepared, and the real casts found it."""
    assert out["missing_before"] == len(out["overloads_prepared"]) > 0   # a fresh process
    assert out["missing_after"] == 0
    assert set(out["overloads_prepared"].values()) == {1}, out["overloads_prepared"]
    assert out["overloads_after"] == out["overloads_prepared"]
    assert out["lit"] > 0


def test_a_cast_and_its_illumination_after_prepare_compile_nothing():
    out = _probe("direct")
    _check_nothing_compiled_after(out)
    messages = [m for _, m in out["reports"]]
    # this run's numba cache decides which, once per installation
    assert messages and messages[0] in (COMPILING, LOADING), messages


@pytest.mark.parametrize("mode", ["cast", "log"])
def test_a_direct_cast_prepares_its_kernels_and_says_so(mode):
    """``cast_camera`` called by a script that prepared nothing makes every kernel
    ready itself, telling its reporter, or, given none, the ``fluoguide.kernels``
    logger, what it is doing (a first run used to be slow for no stated reason)."""
    out = _probe(mode)
    _check_nothing_compiled_after(out)
    assert out["plane_seen"] > 0
    messages = [m for _, m in out["reports"]]
    assert messages and messages[0].startswith((COMPILING, LOADING)), messages
    if mode == "log":
        assert messages[-1].split(": done in ")[0] == messages[0].removesuffix(" ..."), messages


@pytest.mark.slow      # the kernels compiled from nothing: 14-16 s on 2 cores
def test_the_first_frame_s_kernel_compilation_reports_every_second(tmp_path):
    """A truly cold start (numba's cache in an empty folder): correcting a frame
    through the logic announces the compilation and reports its seconds, never
    2 s apart, before the ray cast, which then compiles nothing. The next
    process loads the compiled kernels from the cache."""
    cold = _probe("logic", tmp_path / "numba")
    _check_nothing_compiled_after(cold)
    assert cold["mapped"] > 0
    messages = [m for _, m in cold["reports"]]
    assert messages[0] == COMPILING, messages
    cast = messages.index("ray casting and correcting frame 0")
    assert cast > 1 and messages[cast - 1].startswith(COMPILING + ", "), messages
    times = [cold["start"]] + [t for t, _ in cold["reports"][:cast + 1]]
    seconds = times[-1] - times[0]
    gap = max(b - a for a, b in zip(times, times[1:]))
    print(f"cold compile: {seconds:.1f} s, {cast} reports, longest gap {gap:.2f} s")
    assert seconds > 3.0            # it did compile: the gap below means something
    assert gap <= 2.0, (gap, messages)
    warm = _probe("logic", tmp_path / "numba")
    _check_nothing_compiled_after(warm)
    messages = [m for _, m in warm["reports"]]
    assert messages[0] == LOADING, messages
    assert warm["reports"][messages.index("ray casting and correcting frame 0")][0] \
        - warm["start"] < seconds / 2
