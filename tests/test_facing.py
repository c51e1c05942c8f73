"""Facing: a skeleton the pose model mirrored, while the face faces the camera, is set right.

The reading below is MediaPipe's on a synthetic person with raised arms photographed from azimuth 45
(bench_orbit_truth's ``subject1``): its 2D left shoulder lies on the image's left and its 3D nose behind
the ears, as for a person seen from behind, while the face detector finds the face. Fitted as read, the
body turned 28 deg the wrong way (its shoulders' yaw +28.5 where the truth's is -45).
"""

from __future__ import annotations

import numpy as np

from humanvdm_core.perception.facing import Facing, unmirrored

KEYPOINTS = np.array([[280, 164], [280, 156], [287, 155], [283, 159], [302, 158], [267, 192], [330, 197],
                      [248, 136], [346, 139], [235, 82], [353, 80], [278, 323], [305, 321], [280, 407],
                      [307, 410], [277, 483], [313, 496]], np.float32)
CONFIDENCES = np.array([1, 1, 1, 1, 1, 1, 1, 0.98, 0.93, 0.99, 0.96, 1, 1, 0.98, 0.86, 0.98, 0.94], np.float32)
WORLD = np.array([[-0.057, -0.627, -0.008], [-0.07, -0.649, -0.045], [-0.041, -0.65, -0.026],
                  [-0.071, -0.605, -0.151], [0.048, -0.612, -0.073], [-0.091, -0.504, -0.195],
                  [0.16, -0.535, -0.045], [-0.211, -0.726, -0.229], [0.212, -0.741, 0.023],
                  [-0.234, -0.952, -0.266], [0.216, -0.945, -0.002], [-0.056, 0.003, -0.063],
                  [0.056, -0.004, 0.065], [-0.078, 0.383, 0.009], [0.102, 0.41, 0.121],
                  [-0.036, 0.704, 0.066], [0.141, 0.777, 0.161]], np.float32)


def _yaw_deg(world: np.ndarray, left: int, right: int) -> float:
    """The line right -> left about the vertical, camera axes: 0 along +x (facing the camera), negative with
    the left end nearer the camera."""
    d = world[left] - world[right]
    return float(np.degrees(np.arctan2(d[2], d[0])))


def test_mirrored_needs_a_face_and_both_pose_votes_reading_a_back():
    assert Facing(away=False, ambiguous=False, votes={"face": 1.0, "order": -1.0, "depth": -1.0}).mirrored
    assert not Facing(away=False, ambiguous=False, votes={"face": 1.0, "order": -1.0, "depth": 0.2}).mirrored
    assert not Facing(away=False, ambiguous=False, votes={"face": 1.0, "order": 0.3, "depth": -1.0}).mirrored
    # no face: a back seen as a back (a photo from behind), not a mirrored front
    assert not Facing(away=True, ambiguous=False, votes={"face": -0.5, "order": -1.0, "depth": -1.0}).mirrored


def test_a_mirrored_skeleton_is_set_right_facing_the_camera_and_turned_the_face_s_way():
    assert KEYPOINTS[5, 0] < KEYPOINTS[6, 0]  # as read: the left shoulder on the image's left (a back)
    assert WORLD[0, 2] > WORLD[[3, 4], 2].mean()  # and the nose behind the ears
    kp, conf, world = unmirrored(KEYPOINTS, CONFIDENCES, WORLD)
    # left and right swapped: the left shoulder and hip on the image's right, the confidences with them
    assert kp[5, 0] > kp[6, 0] and kp[11, 0] > kp[12, 0]
    np.testing.assert_array_equal(kp[[5, 6, 9, 10]], KEYPOINTS[[6, 5, 10, 9]])
    np.testing.assert_array_equal(conf[[7, 8]], CONFIDENCES[[8, 7]])
    # the 3D landmarks face the camera: the nose before the ears, by as much as it stood behind them
    assert world[0, 2] < world[[3, 4], 2].mean() - 0.05
    # their projection is unchanged (x and y kept, only relabelled) and the hips' depth stays
    np.testing.assert_allclose(world[:, :2], WORLD[[0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15], :2])
    assert abs(world[[11, 12], 2].mean() - WORLD[[11, 12], 2].mean()) < 1e-6
    # the shoulders and hips turn the way the truth does (-45 deg): as read they turned the other way
    assert -60.0 < _yaw_deg(world, 5, 6) < -20.0 and -60.0 < _yaw_deg(world, 11, 12) < -20.0
    assert _yaw_deg(WORLD, 5, 6) < -120.0  # as read: a back (the line reversed)
    assert unmirrored(KEYPOINTS, CONFIDENCES, None)[2] is None
