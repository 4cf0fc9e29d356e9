"""Paired-point registration (FRE/TRE) and pivot calibration."""

import json

import numpy as np
import pytest

from fluoapp.cli import main as fluo_main
from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.registration import (
    pivot_calibration,
    register_points,
    target_registration_error,
)

T_TRUE = tf.make_rigid(tf.rotation_matrix([0.2, -1.0, 0.5], 2.1), [120.0, -40.0, 300.0])


def _fiducials(n=6, seed=0):
    return np.random.default_rng(seed).uniform(-80, 80, (n, 3))


def test_exact_points_recovered():
    P = _fiducials()
    res = register_points(P, tf.apply_rigid(T_TRUE, P))
    np.testing.assert_allclose(res.transform, T_TRUE, atol=1e-10)
    assert res.fre_mm < 1e-10


def test_fre_and_tre_with_noise_match_theory():
    # Fitzpatrick: E[FRE^2] = (1 - 2/N) sigma_3d^2, sigma_3d^2 = 3 sigma^2
    rng = np.random.default_rng(1)
    sigma, n = 0.3, 8
    fre2, tre = [], []
    target = np.array([[10.0, 20.0, 5.0]])
    for _ in range(400):
        P = _fiducials(n, seed=int(rng.integers(1 << 30)))
        Q = tf.apply_rigid(T_TRUE, P) + rng.normal(0, sigma, P.shape)
        res = register_points(P, Q)
        fre2.append(res.fre_mm ** 2)
        tre.append(target_registration_error(res.transform, target,
                                             tf.apply_rigid(T_TRUE, target))[0])
    expected = (1 - 2 / n) * 3 * sigma ** 2
    assert abs(np.mean(fre2) / expected - 1) < 0.1
    assert 0 < np.median(tre) < 0.5


def test_no_reflection_and_bad_input():
    P = _fiducials(4)
    mirror = P * [1, 1, -1]
    res = register_points(P, mirror)
    assert np.linalg.det(res.transform[:3, :3]) > 0
    with pytest.raises(FluoInputError, match="collinear"):
        register_points([[0, 0, 0], [1, 1, 1], [2, 2, 2]], [[0, 0, 0], [1, 1, 1], [2, 2, 2]])
    with pytest.raises(FluoInputError, match="at least 3"):
        register_points(P[:2], P[:2])
    with pytest.raises(FluoInputError, match="differ in length"):
        register_points(P, P[:3])


def test_pivot_calibration():
    rng = np.random.default_rng(3)
    tip = np.array([2.0, -1.5, 160.0])
    pivot = np.array([50.0, 20.0, -900.0])
    poses = []
    for _ in range(30):
        R = tf.rotvec_to_matrix(rng.normal(0, 0.4, 3))
        poses.append(tf.make_rigid(R, pivot - R @ tip + rng.normal(0, 0.05, 3)))
    res = pivot_calibration(poses)
    assert np.linalg.norm(res["tip_in_tool_mm"] - tip) < 0.2
    assert np.linalg.norm(res["pivot_in_tracker_mm"] - pivot) < 0.2
    assert 0.03 < res["rms_mm"] < 0.15
    with pytest.raises(FluoInputError, match="rotated only"):
        pivot_calibration([tf.make_rigid(np.eye(3), [i, 0, 0]) for i in range(5)])


def test_cli_register(tmp_path, capsys):
    P = _fiducials(5)
    np.savetxt(tmp_path / "m.csv", P, delimiter=",")
    (tmp_path / "f.json").write_text(json.dumps(tf.apply_rigid(T_TRUE, P).tolist()))
    t = np.array([[0.0, 0.0, 0.0]])
    np.savetxt(tmp_path / "tm.csv", t, delimiter=",")
    np.savetxt(tmp_path / "tf.csv", tf.apply_rigid(T_TRUE, t), delimiter=",")
    rc = fluo_main(["calib", "register", "--moving", str(tmp_path / "m.csv"),
                    "--fixed", str(tmp_path / "f.json"), "--targets-moving",
                    str(tmp_path / "tm.csv"), "--targets-fixed", str(tmp_path / "tf.csv"),
                    "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(doc["transform"], T_TRUE, atol=1e-9)
    assert doc["fre_mm"] < 1e-9 and doc["tre_mean_mm"] < 1e-9


def test_cli_pivot(tmp_path, capsys):
    rng = np.random.default_rng(4)
    tip = np.array([0.0, 0.0, 150.0])
    poses = []
    for _ in range(12):
        R = tf.rotvec_to_matrix(rng.normal(0, 0.4, 3))
        poses.append(tf.make_rigid(R, [10.0, 0.0, -800.0] - R @ tip).tolist())
    (tmp_path / "p.json").write_text(json.dumps({"tool_to_tracker": poses}))
    assert fluo_main(["calib", "pivot", "--poses", str(tmp_path / "p.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(doc["tip_in_tool_mm"], tip, atol=1e-9)
    (tmp_path / "bad.json").write_text("{not json")
    assert fluo_main(["calib", "pivot", "--poses", str(tmp_path / "bad.json")]) == 2
    assert "not valid JSON" in capsys.readouterr().err
