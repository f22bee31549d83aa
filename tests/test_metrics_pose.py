"""Pose error and mAA definitions against hand-constructed rotations and error lists."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.metrics.pose import (
    accuracy_curve,
    mean_average_accuracy,
    pose_error_deg,
    rotation_error_deg,
    translation_error_deg,
)


def test_rotation_error_is_the_geodesic_angle():
    R1 = Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix()
    delta = Rotation.from_rotvec(np.radians(7.5) * np.array([0.6, 0.0, 0.8])).as_matrix()
    assert rotation_error_deg(R1, R1 @ delta) == pytest.approx(7.5, abs=1e-6)
    assert rotation_error_deg(R1, R1) == pytest.approx(0.0, abs=1e-5)


def test_translation_error_is_sign_agnostic_and_scale_free():
    t = np.array([1.0, 0.2, -0.3])
    assert translation_error_deg(t, -3.0 * t) == pytest.approx(0.0, abs=1e-5)
    rot = Rotation.from_rotvec(np.radians(12) * np.array([0, 0, 1.0])).as_matrix()
    t2 = np.array([1.0, 0, 0])
    assert translation_error_deg(t2, rot @ t2) == pytest.approx(12.0, abs=1e-6)
    assert translation_error_deg(t2, -(rot @ t2)) == pytest.approx(12.0, abs=1e-6)
    assert math.isinf(translation_error_deg(t2, np.zeros(3)))


def test_pose_error_is_the_max_and_inf_on_failure():
    R = np.eye(3)
    Rb = Rotation.from_rotvec(np.radians(3) * np.array([1.0, 0, 0])).as_matrix()
    t = np.array([0, 0, 1.0])
    t_b = Rotation.from_rotvec(np.radians(6) * np.array([0, 1.0, 0])).as_matrix() @ t
    e, er, et = pose_error_deg(R, t, Rb, t_b)
    assert (er, et) == (pytest.approx(3.0, abs=1e-6), pytest.approx(6.0, abs=1e-6))
    assert e == pytest.approx(6.0, abs=1e-6)
    assert all(math.isinf(x) for x in pose_error_deg(R, t, None, None))


def test_maa_thresholds_are_1_to_tau_inclusive():
    errors = [0.5, 1.0, 2.5, 9.99, 10.0, 30.0, math.inf]
    curve = accuracy_curve(errors, 10)
    # threshold k counts errors <= k
    expected = [sum(e <= k for e in errors) / len(errors) for k in range(1, 11)]
    assert np.allclose(curve, expected)
    assert curve[0] == pytest.approx(2 / 7)  # 0.5 and 1.0 (inclusive)
    assert mean_average_accuracy(errors, 10) == pytest.approx(np.mean(expected))
    assert mean_average_accuracy(errors, 5) == pytest.approx(np.mean(expected[:5]))
    assert mean_average_accuracy([], 10) == 0.0
    assert mean_average_accuracy([math.inf] * 4, 10) == 0.0
    assert mean_average_accuracy([0.0] * 4, 10) == 1.0


def test_rotation_error_is_precise_for_tiny_angles():
    R = Rotation.from_euler("xyz", [30, 40, 50], degrees=True).as_matrix()
    for deg in (1e-4, 3e-3, 0.02):
        d = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.0, 1.0])).as_matrix()
        assert rotation_error_deg(R, R @ d) == pytest.approx(deg, rel=1e-3)
    flip = Rotation.from_rotvec(np.pi * np.array([1.0, 0, 0])).as_matrix()
    assert rotation_error_deg(np.eye(3), flip) == pytest.approx(180.0, abs=1e-6)
