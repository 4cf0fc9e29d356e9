"""Camera response characterisation beyond the basic stack (issue #6): lens
f-number exponent and spectral responsivity from frames with known truth,
auxiliary series kept out of the gain/linearity fit, stack-format checks and
the ``fluo calib radiometry`` command on a stack with all series."""

import json

import numpy as np
import pytest

from fluoapp import cli
from fluoguide.errors import FluoInputError
from FluoCalibLib.radiometry.camera_response import (
    Frame,
    characterize,
    load_stack,
    write_stack,
)
from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera
from FluoCalibLib.radiometry.synthetic import synthetic_lens_spectral_frames, synthetic_stack

# the thesis lens's best-fit exponent (nominal 2), docs/physics.md section 5.2
CAMERA = RadiometricCamera(lens_exponent=1.88)


def _pct(a, b):
    return 100.0 * abs(a - b) / abs(b)


@pytest.fixture(scope="module")
def full_stack():
    frames, truth = synthetic_stack(camera=CAMERA, seed=11)
    # the lens series under the same light as the exposure series
    extra, t_extra = synthetic_lens_spectral_frames(
        camera=CAMERA, radiance_w_per_mm2_sr=truth["radiance_w_per_mm2_sr"], seed=12)
    return frames, extra, {**truth, **t_extra}


def test_lens_exponent_and_spectral_responsivity_match_truth(full_stack):
    frames, extra, truth = full_stack
    r = characterize(frames + extra)
    assert abs(r["lens_exponent"]["alpha"] - 1.88) < 0.02, r["lens_exponent"]
    assert r["lens_exponent"]["f_numbers"] == truth["f_numbers"]
    spec = r["spectral_responsivity"]
    assert spec["wavelength_nm"] == sorted(truth["spectral_e_per_radiance_s"])
    for wl, got in zip(spec["wavelength_nm"], spec["e_per_radiance_s"]):
        assert _pct(got, truth["spectral_e_per_radiance_s"][wl]) < 2.0, wl


def test_extra_series_do_not_bend_the_main_fit(full_stack):
    # frames at other f-numbers and wavelengths are at other radiances: mixed
    # into the exposure series they gave NL ~ 26 % before the series were split
    frames, extra, truth = full_stack
    r = characterize(frames + extra)
    cam = truth["camera"]
    for key in ("gain_adu_per_e", "dark_current_e_per_s", "bias_e", "read_noise_e"):
        assert _pct(r[key], cam[key]) < 3.0, (key, r[key], cam[key])
    assert r["nonlinearity_pct"] < 0.1 and r["linearity_r2"] > 0.99999
    # the same when the main series is labelled with its f-number too
    labelled = [Frame(f.image, f.exposure_s, f.kind, f_number=1.4, name=f.name) for f in frames]
    r2 = characterize(labelled + extra)
    assert _pct(r2["gain_adu_per_e"], cam["gain_adu_per_e"]) < 3.0
    assert r2["nonlinearity_pct"] < 0.1
    assert "lens_exponent" in r2
    # every reported number is finite (no silent NaN)
    for k, v in r.items():
        if isinstance(v, float):
            assert np.isfinite(v), k


def test_frames_of_different_sizes_are_refused(full_stack):
    frames, _, _ = full_stack
    cut = [Frame(f.image[:200, :300], f.exposure_s, f.kind, name=f.name)
           if f.kind == "light" and f.exposure_s > 0.1 else f for f in frames]
    with pytest.raises(FluoInputError, match="differ in size"):
        characterize(cut)


def test_stack_json_errors_name_file_and_field(tmp_path, full_stack):
    frames, extra, _ = full_stack
    folder = write_stack(tmp_path / "s", frames[:4] + extra[:2])
    back, _ = load_stack(folder)
    assert back[-1].f_number == extra[1].f_number
    doc = json.loads((folder / "stack.json").read_text())
    doc["frames"][0]["kind"] = "flat"
    (folder / "stack.json").write_text(json.dumps(doc))
    with pytest.raises(FluoInputError, match=r"frames\[0\]\.kind"):
        load_stack(folder)
    doc["frames"][0]["kind"] = "dark"
    doc["frames"][1]["exposure_s"] = "long"
    (folder / "stack.json").write_text(json.dumps(doc))
    with pytest.raises(FluoInputError, match="exposure must be a number"):
        load_stack(folder)
    (folder / "stack.json").write_text("{not json")
    with pytest.raises(FluoInputError, match="not valid JSON"):
        load_stack(folder)


def test_cli_radiometry_reports_lens_and_spectrum(tmp_path, capsys, full_stack):
    frames, extra, truth = full_stack
    write_stack(tmp_path / "stack", frames + extra, {"truth": truth})
    rc = cli.main(["calib", "radiometry", str(tmp_path / "stack"), "--json",
                   "--out", str(tmp_path / "plots")])
    assert rc in (0, None)
    r = json.loads(capsys.readouterr().out)
    assert _pct(r["gain_adu_per_e"], 1.08) < 3.0
    assert abs(r["lens_exponent"]["alpha"] - 1.88) < 0.02
    assert len(r["spectral_responsivity"]["wavelength_nm"]) == 5
    for name in ("photon_transfer.png", "linearity.png", "dark.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 5000
    # zero-exposure light frame on disk: exit code 2 and one clear line
    doc = json.loads((tmp_path / "stack" / "stack.json").read_text())
    light = next(e for e in doc["frames"] if e["kind"] == "light")
    light["exposure_s"] = 0.0
    (tmp_path / "stack" / "stack.json").write_text(json.dumps(doc))
    assert cli.main(["calib", "radiometry", str(tmp_path / "stack"), "--json"]) == 2
    assert "zero exposure" in capsys.readouterr().err
