"""Tests of FluoCalibLib.transforms against direct constructions and OpenCV."""

import cv2
import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry import transforms as tf


def _random_rotations(n, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        q = rng.normal(size=4)
        out.append(tf.quaternion_to_matrix(q))
    return out


def test_rotation_matrix_axes_right_handed():
    R = tf.rotation_matrix("z", np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    R = tf.rotation_matrix([1, 0, 0], np.pi / 2)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-15)


def test_rotvec_matches_cv2_rodrigues_and_roundtrips():
    rng = np.random.default_rng(1)
    for angle in [0.0, 1e-10, 1e-4, 0.5, 2.0, np.pi - 1e-7, np.pi]:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        rv = axis * angle
        R = tf.rotvec_to_matrix(rv)
        R_cv, _ = cv2.Rodrigues(rv)
        np.testing.assert_allclose(R, R_cv, atol=1e-12)
        back = tf.matrix_to_rotvec(R)
        # near pi the sign of the axis is ambiguous: compare rotations instead
        np.testing.assert_allclose(tf.rotvec_to_matrix(back), R, atol=1e-9)
        assert abs(np.linalg.norm(back) - angle) < 1e-7


def test_quaternion_roundtrip_and_sign():
    for R in _random_rotations(20):
        q = tf.matrix_to_quaternion(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(tf.quaternion_to_matrix(q), R, atol=1e-12)
    # 90 deg about z: q = (cos 45, 0, 0, sin 45)
    q = tf.matrix_to_quaternion(tf.rotation_matrix("z", np.pi / 2))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)


def test_rigid_inverse_and_apply():
    rng = np.random.default_rng(2)
    for R in _random_rotations(5, seed=3):
        T = tf.make_rigid(R, rng.normal(size=3) * 100)
        assert tf.is_rigid(T)
        np.testing.assert_allclose(tf.invert_rigid(T) @ T, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(tf.invert_rigid(T), np.linalg.inv(T), atol=1e-12)
        p = rng.normal(size=(7, 3)) * 50
        ph = np.column_stack([p, np.ones(7)]) @ T.T
        np.testing.assert_allclose(tf.apply_rigid(T, p), ph[:, :3], atol=1e-12)
        np.testing.assert_allclose(tf.apply_rigid(T, p[0]), ph[0, :3], atol=1e-12)
    bad = np.eye(4)
    bad[0, 0] = 1.01
    assert not tf.is_rigid(bad, tol=1e-6)
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    assert not tf.is_rigid(mirror)


def test_slerp_endpoints_midpoint_and_short_path():
    q0 = tf.matrix_to_quaternion(np.eye(3))
    q1 = tf.matrix_to_quaternion(tf.rotation_matrix("x", 1.2))
    np.testing.assert_allclose(tf.slerp(q0, q1, 0.0), q0, atol=1e-12)
    np.testing.assert_allclose(tf.slerp(q0, q1, 1.0), q1, atol=1e-12)
    mid = tf.quaternion_to_matrix(tf.slerp(q0, q1, 0.5))
    np.testing.assert_allclose(mid, tf.rotation_matrix("x", 0.6), atol=1e-12)
    # -q1 is the same rotation: slerp must take the short way
    mid2 = tf.quaternion_to_matrix(tf.slerp(q0, -q1, 0.5))
    np.testing.assert_allclose(mid2, mid, atol=1e-12)
    assert tf.slerp(q0, q1, [0.0, 0.25, 1.0]).shape == (3, 4)


def test_look_at_opencv_frame():
    eye = np.array([0.0, -300.0, 100.0])
    target = np.array([0.0, 0.0, 100.0])
    T = tf.look_at(eye, target, up=(0, 0, 1))
    assert tf.is_rigid(T)
    np.testing.assert_allclose(T[:3, 3], eye)
    # target is on the optical axis, in front of the camera
    p_cam = tf.apply_rigid(tf.invert_rigid(T), target)
    np.testing.assert_allclose(p_cam, [0, 0, 300], atol=1e-12)
    # world up appears upwards in the image (negative camera y)
    up_cam = tf.invert_rigid(T)[:3, :3] @ [0, 0, 1]
    np.testing.assert_allclose(up_cam, [0, -1, 0], atol=1e-12)
    with pytest.raises(FluoInputError):
        tf.look_at(eye, eye)
    with pytest.raises(FluoInputError):
        tf.look_at([0, 0, 0], [0, 0, 10], up=(0, 0, 1))


def test_bad_input():
    with pytest.raises(FluoInputError):
        tf.make_rigid(np.eye(2), [0, 0, 0])
    with pytest.raises(FluoInputError):
        tf.rotation_matrix([0, 0, 0], 1.0)
    with pytest.raises(FluoInputError):
        tf.quaternion_to_matrix([0, 0, 0, 0])
    with pytest.raises(FluoInputError):
        tf.apply_rigid(np.eye(4), np.zeros((3, 2)))
