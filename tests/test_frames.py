"""Frames and rotations: Fossen ZYX, quaternions, slerp, body <-> NED."""

from __future__ import annotations

import numpy as np
import pytest

from lrsensor.errors import GeometryError
from lrsensor.frames import (
    Pose,
    R_from_quat,
    R_ned_from_body,
    body_to_ned,
    euler_from_R_ned_from_body,
    ned_to_body,
    quat_from_R,
    rot_x,
    rot_y,
    rot_z,
    slerp,
)


def test_yaw_90_turns_forward_into_east() -> None:
    R = R_ned_from_body(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_pitch_up_points_forward_axis_up_in_ned() -> None:
    # positive pitch = nose up: body x gets a negative down component
    R = R_ned_from_body(0.0, np.deg2rad(30), 0.0)
    np.testing.assert_allclose(R @ [1, 0, 0], [np.cos(np.pi / 6), 0, -0.5], atol=1e-12)


def test_roll_starboard_down() -> None:
    # positive roll: starboard (body y) goes down
    R = R_ned_from_body(np.deg2rad(90), 0.0, 0.0)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_zyx_order() -> None:
    r, p, y = 0.1, -0.2, 0.3
    np.testing.assert_allclose(R_ned_from_body(r, p, y), rot_z(y) @ rot_y(p) @ rot_x(r))


@pytest.mark.parametrize("angles", [(0.1, 0.2, 0.3), (-1.0, 0.5, 3.0), (0.0, -1.4, -2.0), (3.0, 0.0, 0.0)])
def test_euler_round_trip(angles: tuple[float, float, float]) -> None:
    R = R_ned_from_body(*angles)
    np.testing.assert_allclose(euler_from_R_ned_from_body(R), angles, atol=1e-12)


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        R = R_ned_from_body(*rng.uniform(-3, 3, 3) * np.array([1, 0.5, 1]))
        np.testing.assert_allclose(R_from_quat(quat_from_R(R)), R, atol=1e-12)


def test_slerp_halfway_about_z() -> None:
    q0 = quat_from_R(np.eye(3))
    q1 = quat_from_R(rot_z(np.deg2rad(90)))
    np.testing.assert_allclose(R_from_quat(slerp(q0, q1, 0.5)), rot_z(np.deg2rad(45)), atol=1e-12)
    np.testing.assert_allclose(slerp(q0, q1, 0.0), q0, atol=1e-12)
    np.testing.assert_allclose(R_from_quat(slerp(q0, q1, 1.0)), rot_z(np.deg2rad(90)), atol=1e-12)


def test_slerp_takes_short_way_across_yaw_wrap() -> None:
    q0 = quat_from_R(rot_z(np.deg2rad(179)))
    q1 = quat_from_R(rot_z(np.deg2rad(-179)))
    _, _, yaw = euler_from_R_ned_from_body(R_from_quat(slerp(q0, q1, 0.5)))
    assert abs(abs(yaw) - np.pi) < 1e-9


def test_body_to_ned_round_trip_and_hand_value() -> None:
    pose = Pose(10.0, -2.0, 3.0, 0.0, 0.0, np.pi / 2)
    p_ned = body_to_ned([[1.0, 0.0, 0.0]], pose)
    np.testing.assert_allclose(p_ned, [[10.0, -1.0, 3.0]], atol=1e-12)
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(100, 3))
    pose2 = Pose(1, 2, 3, 0.1, -0.2, 2.5)
    np.testing.assert_allclose(ned_to_body(body_to_ned(pts, pose2), pose2), pts, atol=1e-12)


def test_pose_from_R_p() -> None:
    pose = Pose(1, 2, 3, 0.1, -0.2, 2.5)
    again = Pose.from_R_p(pose.R_ned_from_body, pose.p_ned)
    np.testing.assert_allclose(
        [again.roll_rad, again.pitch_rad, again.yaw_rad, again.north_m], [0.1, -0.2, 2.5, 1.0], atol=1e-12
    )


def test_bad_points_shape() -> None:
    with pytest.raises(GeometryError, match=r"\(N, 3\)"):
        body_to_ned(np.zeros((4, 2)), Pose.identity())
