"""Depth from a single photo: the detector's 3D landmarks, the bone-direction term and the one-sided
silhouette of :mod:`humanvdm_core.body.fit`, and the fit-smpl stage's warning summary.

Synthetic subjects (:mod:`testdata.synthetic`, known true joints) rendered as one photo at
azimuth 0 (384², the way benchmarks/bench_pipeline.py renders its input photos; the child 768²), detected with
MediaPipe and fitted from that photo alone. Measured on one thread (fit 150 iterations, about 4 s;
subject + photo + detection about 5 s): seated knee angle 62-65 deg (true 77), thighs pointing
forward (z 0.9 of the thigh's direction; the old fit from 2D keypoints, a strong pose prior and a
two-sided silhouette bent the knees 22 deg with the thighs pointing down and back); hands-on-hips
elbows 8-10 cm behind the shoulders (old fit: 14-15 cm in front); a gown painted into the mask
changes no fitted width by more than 2% (the old two-sided silhouette spread the arms and legs to
cover it: 40% wider). With the old options the seated, hands-on-hips and gown tests fail.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.fit_smpl import summarize_warnings

SIZE = 384


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def _aim(model, params, bone: str, child: str, direction) -> None:
    """Set ``bone``'s rotation (in place) so that ``child - bone`` points along the world ``direction``
    (the delta-rotation convention of :func:`testdata.synthetic.pose_params`)."""
    import roma

    names = model.joint_names
    parents = list(model.anny.bone_parents)
    zero = model.zero_params(1)
    zero.shape = params.shape
    with torch.no_grad():
        rest = model(zero).joints[0].double()
    pose = params.pose[0].double().clone()
    glob = [torch.eye(3, dtype=torch.float64)] * len(names)
    for i in range(1, len(names)):
        glob[i] = glob[parents[i]] @ roma.rotvec_to_rotmat(pose[i - 1])
    i = names.index(bone)
    a = rest[names.index(child)] - rest[i]
    a, b = a / a.norm(), torch.as_tensor(direction, dtype=torch.float64)
    b = b / b.norm()
    axis = torch.linalg.cross(a, b)
    target = roma.rotvec_to_rotmat(axis / axis.norm() * torch.atan2(axis.norm(), a @ b))
    pose[i - 1] = roma.rotmat_to_rotvec(glob[parents[i]].T @ target)
    params.pose = pose[None].to(params.pose.dtype)


def _forearms_forward(pose_params):
    """A ``pose_params`` replacement: a standing person holding a cup (upper arms down and a little
    forward, forearms forward); ``pose_params`` is the original."""

    def posed(model, name, shape):
        params = pose_params(model, "standing", shape)
        for s, side in ((1.0, "L"), (-1.0, "R")):
            _aim(model, params, f"upperarm01.{side}", f"lowerarm01.{side}", [s * 0.15, -1.0, 0.25])
            _aim(model, params, f"lowerarm01.{side}", f"wrist.{side}", [-s * 0.25, 0.1, 1.0])
        return params

    return posed


def _bowing(pose_params):
    """A ``pose_params`` replacement: a standing person bowing, the chest 40 deg forward."""

    def posed(model, name, shape):
        params = pose_params(model, "standing", shape)
        _aim(model, params, "spine03", "spine01", [0.0, np.cos(np.radians(40)), np.sin(np.radians(40))])
        return params

    return posed


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    """``photo(name)``: a synthetic subject rendered as one photo at azimuth 0, detected and cached:
    (observation, camera, true coco17 in the photo's world frame, metres per world unit)."""
    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    pytest.importorskip("mediapipe", reason="MediaPipe is not installed")
    torch.set_num_threads(1)
    from humanvdm_core.body.fit import observe_frames
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.io import read_npz
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from testdata import synthetic
    from testdata.synthetic import SubjectSpec, make_subject

    specs = {
        "seated": (SubjectSpec(gender=0.3, weight=0.45, pose="seated", seed=1), None),
        "hands-on-hips": (SubjectSpec(gender=0.7, weight=0.6, pose="hands-on-hips", seed=2), None),
        "standing": (SubjectSpec(gender=0.8, weight=0.4, pose="standing", seed=4), None),
        "cup": (SubjectSpec(gender=0.5, weight=0.5, pose="standing", seed=3), _forearms_forward),
        "bow": (SubjectSpec(pose="standing", seed=7), _bowing),
        "a-pose": (SubjectSpec(pose="a-pose", seed=1), None),
        "child": (SubjectSpec(age=0.3, height=0.4, pose="standing", seed=22), None),
        "hand-to-face": (SubjectSpec(pose="hand-to-face", seed=7), None),
        "arms-crossed": (SubjectSpec(pose="arms-crossed", seed=3), None),
        "seated-turned": (SubjectSpec(gender=0.3, weight=0.45, pose="seated", seed=1), None),
    }
    azimuth = {"seated-turned": -45.0}  # the photo taken this far round to the person's right (else 0)
    # MediaPipe leans the child forward in a photo of this size (3 deg at 384), the crossed arms' torso back
    # (10 deg at 384)
    photo_size = {"child": 768, "arms-crossed": 576}
    root = tmp_path_factory.mktemp("fit_depth")
    cache: dict = {}

    def get(name: str):
        if name not in cache:
            spec, pose_fn = specs[name]
            original = synthetic.pose_params
            if pose_fn is not None:  # a pose synthetic.POSES does not have
                synthetic.pose_params = pose_fn(original)
            try:
                obj = make_subject(spec, root / name, texture_size=256 if name not in photo_size else 512)
            finally:
                synthetic.pose_params = original
            truth = read_npz(obj.parent / "truth.npz")
            N = truth["normalized_from_world"].astype(np.float64)
            mesh = normalize_scan(load_scan(obj))
            size = photo_size.get(name, SIZE)
            shot = orbit_cameras(1, size, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([azimuth.get(name, 0.0)]))
            rgba = render_views(mesh, shot, (1.0, 1.0, 1.0)).rgba
            obs, failed = observe_frames(rgba, [0])
            assert obs and not failed, failed
            cam = orbit_cameras(1, size, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([0.0]))
            N = np.linalg.inv(cam.w2c[0]) @ shot.w2c[0] @ N  # the truth where the fit's camera (azimuth 0) sees it
            cache[name] = (obs[0], cam, truth["coco17"] @ N[:3, :3].T + N[:3, 3], 1.0 / float(np.linalg.norm(N[:3, 0])))
        return cache[name]

    return get


def _fit(obs, cam, **options):
    from humanvdm_core.body.fit import FitOptions, fit_body
    from testdata.synthetic import body_model

    return fit_body(body_model(), cam, [obs], FitOptions(iterations=150, **options))


def _torso_z(c: np.ndarray) -> float:
    return float(c[[5, 6, 11, 12], 2].mean())


@pytest.mark.slow
def test_world_keypoints_are_in_camera_axes(photo):
    """The detector's 3D joints: 17 COCO joints, camera axes (x right, y down, z away from the camera)."""
    obs, cam, truth, _ = photo("seated")
    w = obs.world_keypoints
    assert w is not None and w.shape == (17, 3) and w.dtype == np.float32
    assert w[0, 1] < w[11, 1] and w[15, 1] > w[13, 1]  # nose above the hips, ankles below the knees
    assert w[5, 0] > w[6, 0] and w[11, 0] > w[12, 0]  # the person's left on the image's right
    assert w[[13, 14], 2].mean() < w[[11, 12], 2].mean() - 0.15  # a seated person's knees come at the camera
    # bone directions agree with the truth turned into the camera
    true_cam = truth @ cam.w2c[0, :3, :3].T
    bones = [(5, 7), (7, 9), (6, 8), (8, 10), (11, 13), (13, 15), (12, 14), (14, 16)]
    err = [_angle_deg(w[b] - w[a], true_cam[b] - true_cam[a]) for a, b in bones]
    assert float(np.mean(err)) < 25.0, err


@pytest.mark.slow
def test_seated_photo_fits_a_seated_body(photo):
    obs, cam, truth, m_per_unit = photo("seated")
    res = _fit(obs, cam)
    c = res.output.coco17[0].numpy().astype(np.float64)
    for hip, knee, ankle in ((11, 13, 15), (12, 14, 16)):
        fitted = _angle_deg(c[knee] - c[hip], c[ankle] - c[knee])
        true = _angle_deg(truth[knee] - truth[hip], truth[ankle] - truth[knee])
        assert abs(fitted - true) < 25.0, (fitted, true)
        thigh = (c[knee] - c[hip]) / np.linalg.norm(c[knee] - c[hip])
        assert thigh[2] > 0.6 and thigh[2] > abs(thigh[1]), thigh  # forward (+Z, at the camera), not down
    # forearms forward onto the thighs: the wrists in front of the torso (0.19 / 0.13 m, true 0.35; 0.25 /
    # 0.18 without the seated spine term, whose straight spine holds the shoulders back; hanging: about 0)
    assert np.all((c[[9, 10], 2] - _torso_z(c)) * m_per_unit > 0.1), (c[[9, 10], 2] - _torso_z(c)) * m_per_unit
    assert res.reprojection_px[0] < 0.02 * SIZE


def _spine_bend_deg(res) -> float:
    """The fitted spine's bend: the summed rotation angles of its fitted joints (``SPINE_JOINTS``), degrees."""
    from humanvdm_core.body.fit import SPINE_JOINTS
    from testdata.synthetic import body_model

    model = body_model()
    ids = [model.pose_index(n) for n in SPINE_JOINTS if n in model.pose_joint_names]
    return float(np.degrees(res.params.pose[0, ids].norm(dim=-1).sum()))


@pytest.mark.slow
def test_a_seated_photo_fits_a_straight_spine_under_an_upright_torso(photo):
    """A seated person's thighs hide the pelvis, and a single photo shows the torso line, not how the pelvis
    and the chest share it: without the spine term (``spine_prior_weight`` 0) this subject's pelvis rolls
    under a spine bent 27 deg (a slouch pushing the seat out from under the torso; the true spine is
    straight); with it the bend is 4 deg and the torso as upright."""
    obs, cam, truth, _ = photo("seated")
    straight, slouched = _fit(obs, cam), _fit(obs, cam, spine_prior_weight=0.0)
    bend, bend0 = _spine_bend_deg(straight), _spine_bend_deg(slouched)
    lean = _lean_deg(straight.output.coco17[0].numpy().astype(np.float64))
    print(f"spine bend {bend:.1f} deg (without the prior {bend0:.1f}); torso lean {lean:.1f} (true {_lean_deg(truth):.1f})")
    assert bend < 8.0 and bend0 > bend + 10.0, (bend, bend0)
    assert abs(lean - _lean_deg(truth)) < 4.0, (lean, _lean_deg(truth))


@pytest.mark.slow
def test_a_seated_photos_knees_are_raised_so_the_thighs_come_out_level(photo):
    """The detector puts a seated person's 2D knees a tenth of the torso below the knee joints, so the fitted
    thighs sloped down 69 deg from vertical (true 86); raised first (``seated_knees``), 77-79 deg."""
    obs, cam, truth, _ = photo("seated")

    def thighs(c):
        return np.array([_angle_deg(c[k] - c[h], np.array([0.0, -1.0, 0.0])) for h, k in ((11, 13), (12, 14))])

    true = thighs(truth)
    raised = thighs(_fit(obs, cam).output.coco17[0].numpy().astype(np.float64))
    as_read = thighs(_fit(obs, cam, seated_knees=False).output.coco17[0].numpy().astype(np.float64))
    print(f"thighs from vertical: {raised.round(1)} deg raised, {as_read.round(1)} as read, true {true.round(1)}")
    assert np.all(np.abs(raised - true) < 10.0) and np.all(true - as_read > np.abs(raised - true) + 6.0), (
        raised, as_read, true)


def _lean_deg(c: np.ndarray) -> float:
    """The hip centre -> shoulder centre line's lean from +Y, degrees (+ = back, away from +Z)."""
    d = c[[5, 6]].mean(0) - c[[11, 12]].mean(0)
    return float(np.degrees(np.arctan2(-d[2], d[1])))


@pytest.mark.slow
def test_seated_photo_keeps_the_torso_upright(photo):
    """The torso term: without it (upright_weight 0) this fit leans 5.5 deg back (true 0.3, the
    detector's torso 1.5), a seated person reclining in every side view; with it 3.1."""
    obs, cam, truth, _ = photo("seated")
    c = _fit(obs, cam).output.coco17[0].numpy().astype(np.float64)
    assert abs(_lean_deg(c) - _lean_deg(truth)) < 4.0, (_lean_deg(c), _lean_deg(truth))


@pytest.mark.slow
def test_an_upright_child_stays_upright_where_the_detector_leans_her_forward(photo, monkeypatch):
    """MediaPipe leans this upright child's torso 7 deg forward (true 0.1); a lean that small is within its
    error and counts as upright (``TORSO_NOISE_DEG``): the fit is 1.5 deg off, 5 deg without that (the
    test checks that too)."""
    import humanvdm_core.body.fit as fit

    obs, cam, truth, _ = photo("child")
    detected = obs.world_keypoints.astype(np.float64) @ cam.w2c[0, :3, :3]  # camera -> world axes
    assert _lean_deg(detected) < _lean_deg(truth) - 5.0, (_lean_deg(detected), _lean_deg(truth))
    c = _fit(obs, cam).output.coco17[0].numpy().astype(np.float64)
    assert abs(_lean_deg(c) - _lean_deg(truth)) < 3.0, (_lean_deg(c), _lean_deg(truth))
    monkeypatch.setattr(fit, "TORSO_NOISE_DEG", 0.0)
    monkeypatch.setattr(fit, "TORSO_TRUSTED_DEG", 1e-3)
    c = _fit(obs, cam).output.coco17[0].numpy().astype(np.float64)
    assert _lean_deg(c) < _lean_deg(truth) - 4.0, (_lean_deg(c), _lean_deg(truth))


@pytest.mark.slow
def test_arms_crossed_before_the_chest_leave_the_torso_upright(photo, monkeypatch):
    """MediaPipe leans the upright torso (true 0.1 deg) behind these crossed arms 13 deg back; a lean
    backwards that small counts as upright (``TORSO_BACK_NOISE_DEG``) and the fit stands 1.5 deg back;
    with the forward lean's thresholds for it too (the test checks that) it leans 7.5 deg back."""
    import humanvdm_core.body.fit as fit

    obs, cam, truth, _ = photo("arms-crossed")
    detected = obs.world_keypoints.astype(np.float64) @ cam.w2c[0, :3, :3]  # camera -> world axes
    assert _lean_deg(detected) > _lean_deg(truth) + 10.0, (_lean_deg(detected), _lean_deg(truth))
    c = _fit(obs, cam).output.coco17[0].numpy().astype(np.float64)
    assert abs(_lean_deg(c) - _lean_deg(truth)) < 3.0, (_lean_deg(c), _lean_deg(truth))
    monkeypatch.setattr(fit, "TORSO_BACK_NOISE_DEG", fit.TORSO_NOISE_DEG)
    monkeypatch.setattr(fit, "TORSO_BACK_TRUSTED_DEG", fit.TORSO_TRUSTED_DEG)
    c = _fit(obs, cam).output.coco17[0].numpy().astype(np.float64)
    assert _lean_deg(c) > _lean_deg(truth) + 4.0, (_lean_deg(c), _lean_deg(truth))


def test_trusted_lean_counts_a_small_lean_backwards_as_upright():
    """12 deg forward keeps (12 - 10) x 2 = 4 deg; 12 deg back (away from the person's front) keeps
    nothing, and which way is back follows ``front`` (a photo from behind turns it)."""
    from humanvdm_core.body.fit import trusted_lean

    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    a = np.radians(12.0)
    seen = torch.tensor([[0.0, np.cos(a), np.sin(a)], [0.0, np.cos(a), -np.sin(a)]], dtype=torch.float64)
    front = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)

    def leans(out: torch.Tensor) -> np.ndarray:  # degrees, + towards +Z
        return np.degrees(np.arctan2(out[:, 2].numpy(), out[:, 1].numpy()))

    np.testing.assert_allclose(leans(trusted_lean(seen, up)), [4.0, -4.0], atol=1e-6)
    np.testing.assert_allclose(leans(trusted_lean(seen, up, front)), [4.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(leans(trusted_lean(seen, up, -front)), [0.0, -4.0], atol=1e-6)


@pytest.mark.slow
def test_a_bow_the_detector_sees_is_kept(photo):
    """A person bowing 27 deg forward stays bowed (fitted 23 deg, the detector's torso 25): the torso
    term pulls only towards the arc from upright to what the detector sees (a pull to upright alone
    fitted 3 deg), and the stance term's head part, which holds an upright person's head over the
    shoulders, leaves a bowing torso's head alone (applied to it too: 19.4 deg; along the world's horizontal
    rather than the torso's forward, 10.5)."""
    obs, cam, truth, _ = photo("bow")
    assert _lean_deg(truth) < -20.0  # the pose is what we meant
    c = _fit(obs, cam).output.coco17[0].numpy().astype(np.float64)
    assert abs(_lean_deg(c) - _lean_deg(truth)) < 8.0, (_lean_deg(c), _lean_deg(truth))


@pytest.mark.slow
def test_hands_on_hips_keeps_the_elbows_beside_the_body(photo):
    obs, cam, truth, m_per_unit = photo("hands-on-hips")
    res = _fit(obs, cam)
    c = res.output.coco17[0].numpy().astype(np.float64)
    elbow_dz = (c[[7, 8], 2] - c[[5, 6], 2]) * m_per_unit  # + = in front of the shoulders
    wrist_dz = (c[[9, 10], 2] - _torso_z(c)) * m_per_unit
    assert np.all(elbow_dz < 0.03), elbow_dz  # true -0.08 m; the 2D-only fit had them 13 cm in front
    assert np.all(np.abs(wrist_dz) < 0.1), wrist_dz  # hands at the hips, not reaching forward
    limbs = [(5, 7), (7, 9), (6, 8), (8, 10)]
    err = [_angle_deg(c[b] - c[a], truth[b] - truth[a]) for a, b in limbs]
    assert float(np.mean(err)) < 15.0, err


@pytest.mark.slow
def test_forearms_held_forward_come_out_in_front(photo):
    obs, cam, truth, m_per_unit = photo("cup")
    res = _fit(obs, cam)
    c = res.output.coco17[0].numpy().astype(np.float64)
    assert np.all((truth[[9, 10], 2] - _torso_z(truth)) * m_per_unit > 0.2)  # the pose is what we meant
    wrist_dz = (c[[9, 10], 2] - _torso_z(c)) * m_per_unit
    assert np.all(wrist_dz > 0.15), wrist_dz  # true 0.29 m in front of the torso
    for a, b in ((7, 9), (8, 10)):  # forearms nearer horizontal-forward than hanging down
        fore = (c[b] - c[a]) / np.linalg.norm(c[b] - c[a])
        assert fore[2] > 0.7, fore


def _forward_deg(c: np.ndarray, a: int, b: int) -> float:
    """How far the bone a -> b points towards the camera (+Z), degrees."""
    d = c[b] - c[a]
    return float(np.degrees(np.arcsin(d[2] / np.linalg.norm(d))))


@pytest.mark.slow
def test_arms_held_out_to_the_side_stay_in_the_frontal_plane(photo):
    """An A-pose (arms 45 deg out, in the body's plane): MediaPipe tilts the forearms about 20 deg
    towards the camera and the fit followed (+23-28 deg off the truth); frontal_arms keeps them in the
    plane (within 4 deg when measured)."""
    obs, cam, truth, _ = photo("a-pose")
    forearms = ((7, 9), (8, 10))
    for options, held in (({}, True), ({"frontal_arms": False}, False)):
        c = _fit(obs, cam, **options).output.coco17[0].numpy().astype(np.float64)
        err = [abs(_forward_deg(c, a, b) - _forward_deg(truth, a, b)) for a, b in forearms]
        if held:
            assert max(err) < 8.0, err
        else:  # without it the forearms reach towards the camera (so this test can tell)
            assert min(err) > 12.0, err


@pytest.mark.slow
def test_an_arm_held_out_whose_wrist_is_read_short_stays_in_the_image_plane(photo):
    """The A-pose photo with both 2D wrists moved 30 % of the forearm towards the elbow (a sleeve, a
    glove or armour hides the wrist and the detector reads the arm short, as on the three.js Soldier):
    the fit swung the forearms 25-30 deg back out of the image plane to shorten them. With the
    held-out arm's keypoints bounding it from inside only, the forearms stay within a few degrees of
    the truth."""
    from dataclasses import replace

    obs, cam, truth, _ = photo("a-pose")
    keypoints = obs.keypoints.copy()
    for elbow, wrist in ((7, 9), (8, 10)):
        keypoints[wrist] += 0.3 * (keypoints[elbow] - keypoints[wrist])
    short = replace(obs, keypoints=keypoints)
    forearms = ((7, 9), (8, 10))
    for reach in (True, False):
        c = _fit(short, cam, arm_reach_past_keypoints=reach).output.coco17[0].numpy().astype(np.float64)
        err = [abs(_forward_deg(c, a, b) - _forward_deg(truth, a, b)) for a, b in forearms]
        if reach:
            assert max(err) < 6.0, err  # measured 1-2 deg
        else:  # without it the short wrists swing the forearms out of the plane (so this test can tell)
            assert min(err) > 15.0, err  # measured 25-29 deg


def test_reach_directions_only_for_the_elbows_and_wrists_of_arms_held_out():
    """reach_directions on hand-made keypoints: the left arm out to the side gets its shoulder -> wrist
    direction at the elbow and the wrist; the hanging right arm, and every other joint, get none."""
    from humanvdm_core.body.landmarks import held_out_arms, reach_directions

    kp = np.zeros((17, 2))
    kp[[5, 6, 11, 12]] = [[120, 100], [80, 100], [115, 200], [85, 200]]  # shoulders, hips: torso 100 px
    kp[[7, 9]] = [[170, 120], [220, 140]]  # left arm out and down (A-pose)
    kp[[8, 10]] = [[78, 150], [76, 200]]  # right arm hanging
    conf = np.ones(17)
    assert held_out_arms(kp, conf) == [0]
    d = reach_directions(kp, conf)
    line = (kp[9] - kp[5]) / np.linalg.norm(kp[9] - kp[5])
    np.testing.assert_allclose(d[[7, 9]], [line, line])
    assert not np.delete(d, [7, 9], axis=0).any()
    conf[9] = 0.2  # an unsure wrist: not held out
    assert held_out_arms(kp, conf) == [] and not reach_directions(kp, conf).any()


def test_facing_shoulders_turns_a_slight_turn_back_to_the_camera_and_keeps_a_real_one():
    """facing_shoulders on hand-made landmarks (camera axes, the world's up = -y) whose 2D keypoints show
    both arms held out to the side: shoulders turned 4 deg about the vertical come back to facing the
    camera, the arms turning with them about the shoulders' middle (an arm held out to the side then lies
    in the image plane); 9 deg keeps half of what lies beyond the noise (4 deg: the ramp from 6 to 12
    deg), 20 deg all of it; a shoulder line read from behind (turned ~180 deg), a photo whose arms hang
    and every other joint stay as they are."""
    from humanvdm_core.body.landmarks import TURN_NOISE_DEG, TURN_TRUSTED_DEG, facing_shoulders

    up = np.array([0.0, -1.0, 0.0])
    conf = np.ones(17, np.float32)

    def landmarks(turn_deg: float) -> np.ndarray:
        t = np.radians(turn_deg)
        side = np.array([np.cos(t), 0.0, np.sin(t)])  # the person's left, away from the camera when t > 0
        w = np.zeros((17, 3))
        w[0] = [0.0, -0.65, -0.1]
        w[[11, 12]] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
        w[[13, 14, 15, 16]] = [[0.1, 0.45, 0.0], [-0.1, 0.45, 0.0], [0.1, 0.9, 0.0], [-0.1, 0.9, 0.0]]
        centre = np.array([0.0, -0.45, 0.0])
        for s, (shoulder, elbow, wrist) in ((1, (5, 7, 9)), (-1, (6, 8, 10))):  # arms out to the side
            w[shoulder] = centre + s * 0.17 * side
            w[elbow] = centre + s * 0.45 * side
            w[wrist] = centre + s * 0.7 * side
        return w

    def pixels(w: np.ndarray) -> np.ndarray:  # the 2D keypoints: the landmarks seen straight on
        return 300.0 + 400.0 * w[:, :2]

    def turn_of(w: np.ndarray) -> float:
        d = w[5] - w[6]
        return float(np.degrees(np.arctan2(d[2], d[0])))

    assert TURN_NOISE_DEG == 6.0 and TURN_TRUSTED_DEG == 12.0  # the ramp the numbers below assume
    for turn, kept in ((4.0, 0.0), (-4.0, 0.0), (9.0, 6.0), (20.0, 20.0)):
        w = landmarks(turn)
        out = facing_shoulders(w.astype(np.float32), pixels(w), conf, up)
        assert turn_of(out) == pytest.approx(kept, abs=0.05), (turn, turn_of(out))
        np.testing.assert_allclose(out[[0, 1, 2, 3, 4, 11, 12, 13, 14, 15, 16]],
                                   w[[0, 1, 2, 3, 4, 11, 12, 13, 14, 15, 16]], atol=1e-6)
        # the arms turn with the shoulders: the hands lie on the shoulder line, lengths kept
        np.testing.assert_allclose(np.linalg.norm(out[9] - out[10]), 1.4, atol=1e-5)
        assert np.cross(out[5] - out[6], out[9] - out[6]) == pytest.approx(np.zeros(3), abs=1e-5)
    behind = landmarks(0.0)
    behind[[5, 6, 7, 8, 9, 10]] = behind[[6, 5, 8, 7, 10, 9]]
    np.testing.assert_allclose(facing_shoulders(behind.astype(np.float32), pixels(behind), conf, up), behind,
                               atol=1e-6)
    hanging = landmarks(4.0)  # the same turn, the 2D arms hanging beside the body: not a T-pose, kept
    kp = pixels(hanging)
    for shoulder, elbow, wrist in ((5, 7, 9), (6, 8, 10)):
        kp[elbow], kp[wrist] = kp[shoulder] + [0.0, 110.0], kp[shoulder] + [0.0, 210.0]
    np.testing.assert_allclose(facing_shoulders(hanging.astype(np.float32), kp, conf, up), hanging, atol=1e-6)


def _knee_bends_deg(c: np.ndarray) -> list[float]:
    return [_angle_deg(c[k] - c[h], c[a] - c[k]) for h, k, a in ((11, 13, 15), (12, 14, 16))]


def _scan_photo(name: str, size: int, yaw_deg: float = 0.0):
    """The fixture scan ``name`` as the protocol's photo (azimuth 0, 10 deg above, over white): its (size,
    size, 4) RGBA and its camera. Skips without anny, MediaPipe or the fixture; torch on one thread."""
    from pathlib import Path

    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    pytest.importorskip("mediapipe", reason="MediaPipe is not installed")
    scan = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "scans" / name
    if not scan.is_dir():
        pytest.skip(f"fixture scan {scan} not present")
    torch.set_num_threads(1)
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan

    cam = orbit_cameras(1, size, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([0.0]))
    return render_views(normalize_scan(load_scan(scan), yaw_deg=yaw_deg), cam, (1.0, 1.0, 1.0)).rgba[0], cam


@pytest.mark.slow
def test_a_real_person_standing_still_keeps_straight_legs_below_the_hips():
    """RenderPeople Eric (a real scan, T-pose, trousers) as the photo: MediaPipe reads his straight legs
    as knees bent about 35 deg with the feet behind the hips (his 2D shins are a fifth shorter than
    his thighs), and the fit followed (here bends of 24 / 15 deg, the ankles 6 cm behind the hips; in
    the protocol's 768 px photo 28 / 20 deg and 9 cm). The stance term
    of a photo of a person standing still keeps the knees within a few degrees of straight and the
    feet below the hips (here 7 / 5 deg and 1 cm; 11 / 10 deg with the term's free zones of 10 deg
    and 5 cm before 2026-11-27)."""
    from humanvdm_core.body.fit import observe_frames

    rgba, cam = _scan_photo("renderpeople_rp_eric_rigged_001", 576)
    obs, failed = observe_frames(rgba[None], [0])
    assert obs and not failed, failed
    for options, still in (({}, True), ({"stance_weight": 0.0}, False)):
        c = _fit(obs[0], cam, **options).output.coco17[0].numpy().astype(np.float64)
        bends = _knee_bends_deg(c)
        feet = float(c[[15, 16], 2].mean() - c[[11, 12], 2].mean())  # + = in front of the hips
        if still:
            assert max(bends) < 8.0 and abs(feet) < 0.03, (bends, feet)
        else:  # without it the knees bend and the feet trail (so this test can tell)
            assert max(bends) > 20.0 and feet < -0.04, (bends, feet)


@pytest.mark.slow
def test_a_turned_person_is_fitted_as_turned_as_the_detector_reads():
    """RenderPeople Eric (a real scan) turned 30 deg from the camera, as the photo: a turned person's
    shoulders look narrower, which the fit explained by narrower shoulders as much as by a turn. MediaPipe
    turns his shoulders 25.5 deg; without the turn term the fit turned them 12.9 (in the protocol's 768 px
    photo 17.7 of 26.3), with it 23.2, about the term's free 2 deg short of MediaPipe's. The hips, which
    the fit turns about as far as MediaPipe, move 3 deg (29.2 -> 32.0)."""
    from humanvdm_core.body.fit import TURN_FREE_DEG, observe_frames

    rgba, cam = _scan_photo("renderpeople_rp_eric_rigged_001", 576, yaw_deg=-30.0)
    obs, failed = observe_frames(rgba[None], [0])
    assert obs and not failed, failed
    w2c = cam.w2c[0][:3, :3]

    def turn_deg(line: np.ndarray) -> float:  # out of the image plane about the vertical, camera axes
        return float(np.degrees(np.arctan2(line[2], abs(line[0]))))

    world = obs[0].world_keypoints
    seen = turn_deg(world[5] - world[6])
    assert seen < -20.0, seen  # the detector reads a clear turn
    turns = {}
    for weight in (0.0, None):
        options = {} if weight is None else {"turn_weight": weight}
        c = _fit(obs[0], cam, **options).output.coco17[0].numpy().astype(np.float64) @ w2c.T
        turns[weight] = (turn_deg(c[5] - c[6]), turn_deg(c[11] - c[12]))
    (shoulders_off, hips_off), (shoulders, hips) = turns[0.0], turns[None]
    assert shoulders_off > seen + 5.0, (shoulders_off, seen)  # without the term: turned well short
    assert shoulders <= seen + TURN_FREE_DEG + 1.5, (shoulders, seen)
    assert abs(hips - hips_off) < 5.0, (hips, hips_off)


@pytest.mark.slow
def test_a_turned_person_the_detector_mirrors_is_fitted_turned_one_way(tmp_path):
    """A woman with raised arms photographed from 45 deg to her left (`bench_pipeline`'s subject1): MediaPipe
    labels her left and right as if it saw her back, in 2D and in 3D. Phase 1 fitted the body's turn to those
    labels and turned it the wrong way (-35 deg); the left/right decisions after it then mirrored the
    labels, but phase 2 turned only the shoulders back (here to +26), the hips stayed turned the other way
    (-17): a torso twisted by 43 deg. Phase 1 now runs again with the decided labels: shoulders and hips
    both turn her way (+26, +52; the truth turns both +45)."""
    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    pytest.importorskip("mediapipe", reason="MediaPipe is not installed")
    torch.set_num_threads(1)
    from humanvdm_core.body.fit import observe_frames
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from testdata.synthetic import SubjectSpec, make_subject

    spec = SubjectSpec(gender=0.216, age=0.728, muscle=0.304, weight=0.514, height=0.444, proportions=0.557,
                       pose="arms-raised", skin_tone=(160, 108, 72), hair_color=(206, 170, 108),
                       shirt_color=(120, 40, 140), shirt_color2=(230, 110, 150), sleeves="long", shirt_text="33",
                       lower_color=(150, 150, 155), lower_pattern="solid", shoe_color=(120, 40, 140),
                       seed=1298202473)
    mesh = normalize_scan(load_scan(make_subject(spec, tmp_path / "subject1", texture_size=512)))
    photo_cam = orbit_cameras(1, 576, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([45.0]))
    obs, failed = observe_frames(render_views(mesh, photo_cam, (1.0, 1.0, 1.0)).rgba, [0])
    assert obs and not failed, failed
    cam = orbit_cameras(1, 576, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([0.0]))
    w2c = cam.w2c[0][:3, :3]

    def turn_deg(line: np.ndarray) -> float:  # the left -> right line about the vertical, + = left farther
        return float(np.degrees(np.arctan2(line[2], line[0])))

    turns = {}
    for refit in (True, False):
        c = _fit(obs[0], cam, refit_turn=refit).output.coco17[0].numpy().astype(np.float64) @ w2c.T
        turns[refit] = (turn_deg(c[5] - c[6]), turn_deg(c[11] - c[12]))
    (shoulders, hips), (shoulders_once, hips_once) = turns[True], turns[False]
    assert shoulders > 5.0 and hips > 20.0, turns  # both turned her way
    assert abs(hips - shoulders) < 35.0, turns
    assert hips_once < -10.0 and shoulders_once - hips_once > 35.0, turns  # once: twisted (so this test can tell)


def test_standing_still_tells_a_stance_from_a_stride_a_seat_and_hidden_legs():
    """standing_still on hand-made keypoints (a person 400 px tall)."""
    from humanvdm_core.body.landmarks import standing_still

    kp = np.zeros((17, 2))
    kp[[5, 6, 11, 12]] = [[230, 100], [170, 100], [220, 200], [180, 200]]
    kp[[13, 14, 15, 16]] = [[222, 300], [178, 300], [224, 390], [176, 390]]
    conf = np.ones(17)
    mask = np.zeros((480, 400))
    mask[10:410, 150:250] = 1.0
    world = np.zeros((17, 3))
    world[[11, 12, 13, 14, 15, 16]] = [[0.1, 0, 0], [-0.1, 0, 0], [0.1, 0.45, -0.05], [-0.1, 0.45, -0.05],
                                       [0.1, 0.9, 0.02], [-0.1, 0.9, 0.02]]
    assert standing_still(kp, conf, world, mask)
    stride = kp.copy()
    stride[16, 1] = 370  # one ankle 5 % of the height higher: a step
    seated = kp.copy()
    seated[[13, 14]] = [[222, 240], [178, 240]]  # thighs foreshortened: pointing at the camera
    hidden = conf.copy()
    hidden[[15, 16]] = 0.2  # ankles under a gown
    bent = world.copy()
    bent[[13, 14], 2] = -0.4  # the detector's knees bent about 80 deg
    for k, c, w in ((stride, conf, world), (seated, conf, world), (kp, hidden, world), (kp, conf, bent)):
        assert not standing_still(k, c, w, mask)


def test_only_a_seated_persons_knees_are_raised():
    """seated / raise_seated_knees on hand-made landmarks: both thighs' 3D landmarks pointing at the camera
    raise both 2D knees by a share of the 2D torso that shrinks as the camera rises (read off the world's
    up in the camera's axes; seen from 30 deg above the same thighs still count); thighs hanging down,
    one thigh forward (a step), thighs pointing away (a seated person seen from behind), an unsure knee
    or no 3D landmarks leave them. A knee whose 2D thigh is long (the thigh seen at a slant) is raised less,
    from ``KNEE_RAISE_NONE`` of the torso on not at all."""
    from humanvdm_core.body.landmarks import (
        KNEE_RAISE_FULL,
        KNEE_RAISE_LEVEL,
        KNEE_RAISE_NONE,
        KNEE_RAISE_PER_DEG,
        raise_seated_knees,
        seated,
    )

    kp = np.zeros((17, 2))
    kp[[5, 6, 11, 12, 13, 14]] = [[230, 100], [170, 100], [220, 200], [180, 200], [222, 240], [178, 240]]
    conf = np.ones(17)
    world = np.zeros((17, 3))
    world[[11, 12]] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    world[[13, 14]] = [[0.1, 0.15, -0.4], [-0.1, 0.15, -0.4]]  # 69 deg from straight down, at the camera
    def up(elevation):  # the world's up in the axes of a camera that many degrees above
        return np.array([0.0, -np.cos(np.radians(elevation)), -np.sin(np.radians(elevation))])

    raised = {}
    for elevation in (10.0, 30.0):
        assert seated(conf, world, up(elevation))
        raised[elevation] = raise_seated_knees(kp, conf, world, up(elevation))
        share = KNEE_RAISE_LEVEL - KNEE_RAISE_PER_DEG * elevation
        assert np.allclose(raised[elevation][[13, 14], 1], 240 - share * 100)
        assert np.array_equal(raised[elevation][:13], kp[:13])
    assert raised[30.0][13, 1] > raised[10.0][13, 1] + 5  # raised less from above
    slanted = kp.copy()  # seen at a slant: the left 2D thigh 0.7 of the torso, the right one 0.55
    slanted[[13, 14]] = [[290, 200], [125, 200]]
    lifted = raise_seated_knees(slanted, conf, world, up(10.0))
    part = (KNEE_RAISE_NONE - 0.55) / (KNEE_RAISE_NONE - KNEE_RAISE_FULL)
    assert lifted[13, 1] == 200 and np.isclose(lifted[14, 1], 200 - part * (KNEE_RAISE_LEVEL - KNEE_RAISE_PER_DEG * 10) * 100)
    hanging, step, away = world.copy(), world.copy(), world.copy()
    hanging[[13, 14]] = [[0.1, 0.45, -0.05], [-0.1, 0.45, -0.05]]
    step[14] = [-0.1, 0.45, -0.05]
    away[[13, 14], 2] = 0.4
    unsure = conf.copy()
    unsure[13] = 0.2
    for c, w in ((conf, hanging), (conf, step), (conf, away), (unsure, world), (conf, None)):
        assert not seated(c, w, up(10.0)) and np.array_equal(raise_seated_knees(kp, c, w, up(10.0)), kp)


def test_frontal_arms_moves_only_arms_held_out_to_the_side():
    """frontal_arms on hand-made landmarks (a level camera: the frontal plane is the image plane); a seated
    person's arms stay where the detector put them in a single photo."""
    from humanvdm_core.body.landmarks import frontal_arms

    up = np.array([0.0, -1.0, 0.0])
    world = np.zeros((17, 3))
    world[[5, 6]] = [[0.2, -0.5, 0.0], [-0.2, -0.5, 0.0]]
    world[[11, 12]] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    kp = np.zeros((17, 2))
    kp[[5, 6, 11, 12]] = [[260, 100], [180, 100], [240, 200], [200, 200]]
    conf = np.ones(17)
    # left arm: 45 deg out in the image, straight, its 3D forearm tilted towards the camera (-z)
    kp[[7, 9]] = [[300, 140], [340, 180]]
    world[7] = world[5] + [0.2, 0.2, -0.03]
    world[9] = world[7] + [0.15, 0.15, -0.12]
    # right arm: hanging in the image, its forearm forward in 3D (holding a cup)
    kp[[8, 10]] = [[175, 150], [178, 190]]
    world[8] = world[6] + [-0.02, 0.28, 0.0]
    world[10] = world[8] + [0.0, 0.05, -0.25]
    out = frontal_arms(world.astype(np.float32), kp, conf, up)
    np.testing.assert_allclose(out[[7, 9], 2], world[5, 2], atol=1e-6)  # the left arm in the plane
    for a, b in ((5, 7), (7, 9)):  # its bone lengths kept
        assert np.linalg.norm(out[b] - out[a]) == pytest.approx(np.linalg.norm(world[b] - world[a]), rel=1e-5)
    keep = [i for i in range(17) if i not in (7, 9)]
    np.testing.assert_allclose(out[keep], world[keep], atol=1e-6)  # the hanging arm and the rest unchanged
    # a bent arm (hands on the hips: the forearm turns back in), an arm pointing at the camera (short in
    # the image) and an unsure wrist keep their depth
    bent = kp.copy()
    bent[9] = [280, 200]
    short = kp.copy()
    short[[7, 9]] = [[270, 105], [280, 110]]
    unsure = conf.copy()
    unsure[9] = 0.3
    for k, c in ((bent, conf), (short, conf), (kp, unsure)):
        np.testing.assert_allclose(frontal_arms(world.astype(np.float32), k, c, up), world, atol=1e-6)
    # a seated person (thighs at the camera) keeps a single photo's arms: a straight arm reaches for the knees
    seated = world.copy()
    seated[[13, 14]] = [[0.1, 0.15, -0.4], [-0.1, 0.15, -0.4]]
    np.testing.assert_allclose(frontal_arms(seated.astype(np.float32), kp, conf, up), seated, atol=1e-6)
    laid = frontal_arms(seated.astype(np.float32), kp, conf, up, turned=False)  # an orbit's frame: laid as seen
    np.testing.assert_allclose(laid[[7, 9], 2], world[5, 2], atol=1e-6)


def test_an_arm_held_out_from_a_turned_body_is_read_in_its_plane():
    """A body turned 45 deg from a level camera, its right arm held out 35 deg from hanging in the body's
    own plane: the photo shows it 26 deg from hanging (its sideways extent narrowed by cos 45), under
    held_out_arms' 30, so frontal_arms left its 3D forearm where MediaPipe tilted it. Read in the turned
    plane it is held out, and frontal_arms puts it into that plane."""
    from humanvdm_core.body.landmarks import ARM_OUT_DEG, frontal_arms, held_out_arms

    up = np.array([0.0, -1.0, 0.0])
    c = np.cos(np.radians(45.0))
    world = np.zeros((17, 3))
    world[[5, 6]] = [[0.2 * c, -0.5, -0.2 * c], [-0.2 * c, -0.5, 0.2 * c]]  # the left shoulder nearer
    world[[11, 12]] = [[0.1 * c, 0.0, -0.1 * c], [-0.1 * c, 0.0, 0.1 * c]]
    out_dir = np.array([-c, 0.0, c])  # the right arm's sideways direction in the body's plane
    arm = np.sin(np.radians(35.0)) * out_dir + np.cos(np.radians(35.0)) * np.array([0.0, 1.0, 0.0])
    world[8] = world[6] + 0.28 * arm
    world[10] = world[8] + 0.25 * arm + [0.0, 0.0, -0.12]  # the forearm tilted towards the camera
    kp = np.zeros((17, 2))
    px = 400.0  # pixels per metre, orthographic
    for j in (5, 6, 11, 12):
        kp[j] = [200 + px * world[j, 0], 200 + px * world[j, 1]]
    for j in (8, 10):  # the arm as the photo shows it, in the body's plane
        kp[j] = [200 + px * (world[6, 0] + (world[j, 1] - world[6, 1]) * np.tan(np.radians(35.0)) * -c),
                 200 + px * world[j, 1]]
    kp[[7, 9]] = kp[5] + [0.0, 100.0], kp[5] + [0.0, 200.0]  # the left arm hangs
    conf = np.ones(17)
    seen = np.degrees(np.arctan2(abs(kp[8, 0] - kp[6, 0]), kp[8, 1] - kp[6, 1]))
    assert seen < ARM_OUT_DEG < 35.0, seen
    assert held_out_arms(kp, conf) == [] and held_out_arms(kp, conf, turn_cos=c) == [1]
    out = frontal_arms(world.astype(np.float32), kp, conf, up)
    normal = np.cross(world[5] - world[6], up)
    normal /= np.linalg.norm(normal)
    assert abs((out[10] - out[6]) @ normal) < 1e-5 < abs((world[10] - world[6]) @ normal)  # now in the plane
    np.testing.assert_allclose(out[[7, 9]], world[[7, 9]], atol=1e-6)  # the hanging arm unchanged


def test_a_far_forearm_the_detector_points_at_the_camera_takes_the_photos_direction():
    """A body turned 45 deg from a level camera, its far (right) arm held out 40 deg from hanging in the
    body's plane, straight, as the photo shows it; the detector points that forearm at the camera. Laid
    into the body's plane it would hang down beside the hip (its image direction 40 deg from the photo's),
    so frontal_arms lifts the photo's forearm into the plane: it points away from the camera, along the
    upper arm, its length kept."""
    from humanvdm_core.body.landmarks import frontal_arms

    up = np.array([0.0, -1.0, 0.0])
    c = np.cos(np.radians(45.0))
    world = np.zeros((17, 3))
    world[[5, 6]] = [[0.2 * c, -0.5, -0.2 * c], [-0.2 * c, -0.5, 0.2 * c]]  # the left shoulder nearer
    world[[11, 12]] = [[0.1 * c, 0.0, -0.1 * c], [-0.1 * c, 0.0, 0.1 * c]]
    arm = np.sin(np.radians(40.0)) * np.array([-c, 0.0, c]) + np.cos(np.radians(40.0)) * np.array([0.0, 1.0, 0.0])
    world[8] = world[6] + 0.28 * arm
    towards = np.array([-0.5, 0.6, -0.6])  # the detector's forearm, pointed at the camera
    world[10] = world[8] + 0.25 * towards / np.linalg.norm(towards)
    truth = world[8] + 0.25 * arm
    kp = np.zeros((17, 2))
    for j in (5, 6, 11, 12, 8):
        kp[j] = 200 + 400 * world[j, :2]  # orthographic, 400 px a metre
    kp[10] = 200 + 400 * truth[:2]
    kp[[7, 9]] = kp[5] + [0.0, 100.0], kp[5] + [0.0, 200.0]  # the left arm hangs
    out = frontal_arms(world.astype(np.float32), kp, np.ones(17), up)
    np.testing.assert_allclose(out[10], truth, atol=1e-5)
    np.testing.assert_allclose(out[[6, 8]], world[[6, 8]], atol=1e-5)  # the upper arm was in the plane already


def test_arms_read_short_tells_a_detector_contradicting_itself_from_foreshortening():
    """arms_read_short / rebuild_arms on hand-made landmarks: a T-pose arm whose 2D wrist sits on the
    elbow while its 3D landmarks lie in the image plane is read short and redrawn along them; an arm
    pointing at the camera (short in 2D because its 3D direction leaves the plane), an arm of normal
    length and an unsure arm are not."""
    from humanvdm_core.body.landmarks import FOREARM_TORSO, UPPER_ARM_TORSO, arms_read_short, rebuild_arms

    world = np.zeros((17, 3))
    world[[5, 6]] = [[0.2, -0.5, 0.0], [-0.2, -0.5, 0.0]]
    world[[11, 12]] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    kp = np.zeros((17, 2))
    kp[[5, 6, 11, 12]] = [[260, 100], [180, 100], [250, 200], [190, 200]]  # torso 100 px
    conf = np.ones(17)
    # the left arm held out sideways in 3D; in 2D its elbow 55 px out, its wrist 8 px beyond the elbow
    world[7], world[9] = world[5] + [0.28, 0.0, -0.02], world[5] + [0.53, 0.0, -0.05]
    kp[[7, 9]] = [[315, 100], [323, 100]]
    # the right arm points at the camera in 3D and is short in 2D, as it should be
    world[8], world[10] = world[6] + [-0.05, 0.02, -0.27], world[6] + [-0.08, 0.03, -0.52]
    kp[[8, 10]] = [[170, 104], [164, 106]]
    assert arms_read_short(kp, conf, world) == [0]
    out = rebuild_arms(kp, world, [0])
    fore = world[9] - world[7]
    np.testing.assert_allclose(out[7], kp[5] + UPPER_ARM_TORSO * 100.0 * np.array([0.28, 0.0]) / np.hypot(0.28, 0.02),
                               atol=0.01)
    np.testing.assert_allclose(out[9], out[7] + FOREARM_TORSO * 100.0 * fore[:2] / np.linalg.norm(fore), atol=0.01)
    keep = [i for i in range(17) if i not in (7, 9)]
    np.testing.assert_allclose(out[keep], kp[keep])
    long_enough = kp.copy()
    long_enough[9] = [360, 100]  # the forearm 45 px: 0.9 of the 50 its 3D direction implies
    unsure = conf.copy()
    unsure[9] = 0.3
    assert arms_read_short(long_enough, conf, world) == [] and arms_read_short(kp, unsure, world) == []


@pytest.mark.slow
def test_an_armoured_figure_keeps_its_arms_out_to_the_side_and_its_head_over_the_shoulders():
    """The three.js Soldier (a faceless armoured game character in a T-pose, fixture scan) as the
    protocol's 768 px photo: MediaPipe's 2D right wrist lands half way along the forearm (0.54 of the
    length its 3D landmarks imply) and the fit swung that forearm 44 deg backwards to match, a beam
    from the side. Redrawn along the 3D landmarks, it stays within 25 deg of the image plane, and the
    run says what it guessed. Its hood hides the neck (the 2D ears 12.6 cm above the shoulders, Eric's
    15.9): the fit tilted the head 7.5 cm towards the camera to shorten it; the stance term of a
    person standing still keeps the ears within a few centimetres of the shoulders (here within one)."""
    import tempfile
    from pathlib import Path

    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.io import write_png

    rgba, _ = _scan_photo("threejs_soldier", 768, yaw_deg=180.0)  # the Soldier faces -Z
    with tempfile.TemporaryDirectory() as tmp:
        photo = Path(tmp) / "soldier.png"
        write_png(photo, rgba)
        proxy = build_body_proxy(photo, geometry="body")
    c = proxy.coco17
    for elbow, wrist in ((7, 9), (8, 10)):
        fore = c[wrist] - c[elbow]
        out_of_plane = np.degrees(np.arcsin(abs(fore[2]) / np.linalg.norm(fore)))
        assert out_of_plane < 25.0, (elbow, out_of_plane)  # the right forearm was 44 deg out before
    assert any("soldier.png: the pose model's 2D right arm is much shorter than its 3D landmarks show" in w
               for w in proxy.warnings), proxy.warnings
    ears_forward = float(c[[3, 4], 2].mean() - c[[5, 6], 2].mean())  # the camera looks along -Z
    assert abs(ears_forward) < 0.045, ears_forward  # 0.075 without the head's part of the stance term


def test_an_upright_figure_the_detector_reads_lying_down_is_not_turned(tmp_path):
    """The three.js Soldier in its T-pose turned 35 deg (fixture scan, the protocol's 768 px photo): on the
    whole photo MediaPipe's keypoints run across it, head to the right, and the photo used to be turned
    a quarter so the orbit showed a figure lying on its side. The turned photo's detection does not
    confirm it (it reads the figure lying the other way): the photo stays upright, with no warning that
    it was turned, and the keypoints read within the figure's own box stand upright."""
    from types import SimpleNamespace

    from humanvdm_core.body_prior import prepare_input_view
    from humanvdm_core.io import write_png
    from humanvdm_core.perception import detect_person
    from humanvdm_core.perception.detect import stands_upright, upright_turns

    rgba, _ = _scan_photo("threejs_soldier", 768, yaw_deg=180.0 + 35.0)  # the Soldier faces -Z
    photo = tmp_path / "soldier_turned.png"
    write_png(photo, rgba)
    assert upright_turns(detect_person(photo)) != 0  # the misreading this test is about
    view = prepare_input_view(photo, 768)
    assert not any("so they stand upright" in w for w in view.warnings), view.warnings
    assert stands_upright(SimpleNamespace(keypoints=view.keypoints, confidences=view.confidences))


@pytest.mark.slow
def test_a_head_bowed_before_the_shoulders_stays_bowed(tmp_path, monkeypatch):
    """A synthetic person standing still with the neck bent 45 deg forward (reading, looking at a
    phone; seed 3): the truth's ears stand 8 cm before the shoulders and the fit finds them there. The
    face mesh reads the face pitched beyond BOWED_DEG, so the stance term leaves the head where the
    other terms put it; held over the shoulders regardless, the fit knocked it 10 cm back (and the
    orbit's side IoU fell 0.78 -> 0.55)."""
    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    pytest.importorskip("mediapipe", reason="MediaPipe is not installed")
    torch.set_num_threads(1)
    from humanvdm_core.body_prior import build_body_proxy
    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.io import write_png
    from humanvdm_core.perception import facing
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalize_scan
    from testdata.synthetic import SubjectSpec, make_subject

    obj = make_subject(SubjectSpec(pose="head-bowed", seed=3), tmp_path / "bowed", texture_size=256)
    cam = orbit_cameras(1, 576, 33.8, 10.0, framing_radius(), azimuths_deg=np.array([0.0]))
    photo = tmp_path / "bowed.png"
    write_png(photo, render_views(normalize_scan(load_scan(obj)), cam, (1.0, 1.0, 1.0)).rgba[0])

    def ears_before_shoulders() -> float:
        c = build_body_proxy(photo, geometry="body").coco17
        return float(c[[3, 4], 2].mean() - c[[5, 6], 2].mean())  # the camera looks along -Z

    assert ears_before_shoulders() > 0.06
    monkeypatch.setattr(facing, "BOWED_DEG", 90.0)  # no face counts as bowed: the head is held back
    assert ears_before_shoulders() < 0.03


def test_the_stance_term_holds_the_head_over_the_shoulders_only_when_asked():
    """_Problem.stance_term on hand-made joints (straight legs, the feet below the hips): the ears'
    centre 7 cm before the shoulders, or 3 cm behind them, costs with ``head`` and nothing without;
    2 cm before (where people hold it) costs nothing either way. Before and behind are the body's own
    (its left shoulder x its spine), not the camera's: the same body turned to face away costs the same."""
    from humanvdm_core.body.fit import STANCE_HEAD_AHEAD, STANCE_HEAD_FREE, _Problem

    c = torch.zeros(17, 3, dtype=torch.float64)
    c[5], c[6] = torch.tensor([0.2, 1.45, 0.0]), torch.tensor([-0.2, 1.45, 0.0])  # shoulders
    c[11], c[12] = torch.tensor([0.1, 0.95, 0.0]), torch.tensor([-0.1, 0.95, 0.0])  # hips
    c[13], c[14] = c[11] - torch.tensor([0.0, 0.45, 0.0]), c[12] - torch.tensor([0.0, 0.45, 0.0])  # knees
    c[15], c[16] = c[13] - torch.tensor([0.0, 0.45, 0.0]), c[14] - torch.tensor([0.0, 0.45, 0.0])  # ankles
    forward = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)  # the camera looks at the body's front
    away = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))  # turned 180 deg about +Y
    for ahead, costs in ((0.07, True), (0.02, False), (-0.03, True)):
        c[3], c[4] = torch.tensor([0.07, 1.6, ahead]), torch.tensor([-0.07, 1.6, ahead])  # ears
        assert float(_Problem.stance_term(c, forward)) == 0.0
        with_head = float(_Problem.stance_term(c, forward, head=True))
        assert (with_head > 0.0) == costs, (ahead, with_head)
        assert float(_Problem.stance_term(c @ away, forward, head=True)) == pytest.approx(with_head)
    assert STANCE_HEAD_AHEAD - STANCE_HEAD_FREE <= 0.0 and STANCE_HEAD_AHEAD + STANCE_HEAD_FREE < 0.07


def test_onto_the_head_moves_only_wrists_on_the_head():
    """onto_the_head on hand-made landmarks (camera axes: x right, y down, z away from the camera): a
    wrist beside the face but 0.25 m before the nose moves back to the head's middle, as does one on
    the crown taken level with the ears; a wrist at the hip, an unsure one, or any wrist when the head
    is unsure, keeps its depth; nothing else moves. Under an elbow raised above the shoulder, a wrist
    further out and unsure (the far hand behind the head) is on it too; not with the elbow at the
    shoulder's height, nor further out (a wave)."""
    from humanvdm_core.body.landmarks import hands_on_head, onto_the_head

    world = np.zeros((17, 3))
    world[0] = [0.0, -0.65, -0.2]  # nose, 0.1 m before the ears
    world[[3, 4]] = [[0.07, -0.66, -0.1], [-0.07, -0.66, -0.1]]
    world[[5, 6]] = [[0.18, -0.5, 0.0], [-0.18, -0.5, 0.0]]
    world[10] = [-0.08, -0.52, -0.45]  # right palm on the cheek, taken 0.25 m before the nose
    world[9] = [0.1, 0.0, -0.1]  # left hand at the hip
    conf = np.ones(17)
    assert hands_on_head(world, conf) == [10]
    out = onto_the_head(world.astype(np.float32), conf)
    assert out[10, 2] == pytest.approx(-0.15)  # halfway between the nose and the ears
    keep = [i for i in range(17) if i != 10]
    np.testing.assert_allclose(out[keep], world[keep], atol=1e-6)
    np.testing.assert_allclose(out[10, :2], world[10, :2], atol=1e-6)
    crown = world.copy()
    crown[10] = [-0.07, -0.8, -0.1]  # on top of the head, taken level with the ears
    assert onto_the_head(crown.astype(np.float32), conf)[10, 2] == pytest.approx(-0.15)
    for c in (np.where(np.arange(17) == 10, 0.3, 1.0), np.where(np.arange(17) == 0, 0.3, 1.0),
              np.where(np.isin(np.arange(17), [3, 4]), 0.3, 1.0)):
        assert hands_on_head(world, c) == []
        np.testing.assert_allclose(onto_the_head(world.astype(np.float32), c), world, atol=1e-6)
    # seen at a slant: the far hand behind the head, unsure and 0.25 m from its centre, under a raised elbow
    behind = world.copy()
    behind[10] = [-0.22, -0.78, 0.05]
    behind[8] = [-0.3, -0.62, 0.0]  # the elbow 0.12 m above the shoulder
    unsure = np.where(np.arange(17) == 10, 0.2, 1.0)
    assert hands_on_head(behind, unsure) == [10]
    for wrist, elbow in (([-0.22, -0.78, 0.05], [-0.3, -0.5, 0.0]),  # the elbow at the shoulder's height
                         ([-0.3, -0.88, 0.05], [-0.3, -0.62, 0.0])):  # the hand 0.37 m out: waving
        away = world.copy()
        away[10], away[8] = wrist, elbow
        assert hands_on_head(away, unsure) == []


@pytest.mark.slow
def test_a_palm_on_the_cheek_is_fitted_at_the_face_not_before_it(photo):
    """The right palm on the cheek, the forearm raised from an elbow in front of the chest: MediaPipe
    puts the wrist 0.25 m before the nose and the fit followed (0.36 m before it, measured at 384 px);
    onto_the_head brings it to the face (0.10 m before the nose, measured; truth 0.03 m behind it)."""
    obs, cam, truth, m_per_unit = photo("hand-to-face")
    assert abs(truth[10, 2] - truth[0, 2]) * m_per_unit < 0.05  # the pose is what we meant
    for options, touching in (({}, True), ({"hands_on_head": False}, False)):
        c = _fit(obs, cam, **options).output.coco17[0].numpy().astype(np.float64)
        wrist_dz = (c[10, 2] - c[0, 2]) * m_per_unit  # + = before the nose
        if touching:
            assert wrist_dz < 0.15, wrist_dz
            assert (c[8, 2] - c[6, 2]) * m_per_unit > 0.1  # the elbow still before the shoulder (truth 0.24 m)
        else:  # without it the hand stands far before the face (so this test can tell)
            assert wrist_dz > 0.2, wrist_dz


def _widths(res) -> np.ndarray:
    c = res.output.coco17[0].numpy()
    v = res.output.vertices[0].numpy()
    below_hips = v[v[:, 1] < c[[11, 12], 1].mean()]
    return np.array([np.ptp(v[:, 0]), np.ptp(below_hips[:, 0]), np.linalg.norm(c[11] - c[12]),
                     np.linalg.norm(c[13] - c[14]), np.linalg.norm(c[15] - c[16]), np.linalg.norm(c[9] - c[10])])


@pytest.mark.slow
def test_one_sided_silhouette_ignores_a_gown(photo):
    """A mask much wider than the body (a gown from the hips down, everything dilated) leaves the
    fitted body's widths alone; the two-sided silhouette (silhouette_cover_weight) would widen it."""
    import cv2

    obs, cam, _, _ = photo("standing")
    kp = obs.keypoints
    gown = obs.mask.copy()
    hip_y, ankle_y = kp[[11, 12], 1].mean(), kp[[15, 16], 1].mean()
    cx, hw = kp[[11, 12], 0].mean(), abs(kp[11, 0] - kp[12, 0])
    cv2.fillPoly(gown, [np.array([[cx - hw, hip_y], [cx + hw, hip_y], [cx + 2.6 * hw, ankle_y],
                                  [cx - 2.6 * hw, ankle_y]], np.int32)], 1.0)
    gown = cv2.dilate((gown > 0.5).astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (31, 31)))
    assert gown.sum() > 1.8 * (obs.mask > 0.5).sum()
    from dataclasses import replace

    in_gown = replace(obs, mask=gown.astype(np.float32))
    plain = _widths(_fit(obs, cam))
    gowned = _widths(_fit(in_gown, cam))
    np.testing.assert_allclose(gowned, plain, rtol=0.05)
    # the old two-sided term does widen it (so this test can tell)
    covered = _widths(_fit(in_gown, cam, silhouette_cover_weight=0.3))
    assert np.max(covered / plain) > 1.15, covered / plain


def test_bone_term_and_independent_3d_swaps():
    """The bone-direction term is 0 at the truth; 3D landmarks whose arms are labelled the other way
    round are swapped back on their own, without touching the 2D decision."""
    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    from humanvdm_core.body.fit import FitOptions, FrameObservation, _Problem, project
    from humanvdm_core.cameras import orbit_cameras
    from testdata.synthetic import body_model, pose_params

    model = body_model()
    params = pose_params(model, "walking", model.default_shape(1))
    with torch.no_grad():
        out = model(params)
    cams = orbit_cameras(2, 256, azimuths_deg=np.array([0.0, 30.0]))
    w2c = torch.as_tensor(cams.w2c, dtype=model.dtype)
    px, _ = project(out.coco17[0], w2c, torch.as_tensor(cams.K, dtype=model.dtype))
    world = (out.coco17[0] @ w2c[:, :3, :3].transpose(1, 2)).numpy() * 0.7 + 3.0  # any scale and origin
    swapped = world[1].copy()
    for a, b in ((5, 6), (7, 8), (9, 10)):
        swapped[[a, b]] = swapped[[b, a]]
    obs = [FrameObservation(0, px[0].numpy(), np.ones(17, np.float32), np.ones((32, 32), np.float32), [], world[0]),
           FrameObservation(1, px[1].numpy(), np.ones(17, np.float32), np.ones((32, 32), np.float32), [], swapped)]
    problem = _Problem(model, cams, obs, FitOptions())
    assert float(problem.bone_direction_term(out.coco17[0], range(9, 12))) < 1e-4  # hips, spine, neck agree
    assert float(problem.bone_direction_term(out.coco17[0])) > 0.05  # frame 1's arms do not (yet)
    problem.decide_swaps(out.coco17[0])
    assert not problem.swapped.any()
    assert problem.swapped_3d.tolist() == [[False, False, False], [False, True, False]]
    assert float(problem.bone_direction_term(out.coco17[0])) < 1e-4
    with torch.no_grad():
        rest = model(model.zero_params(1))
    assert float(problem.bone_direction_term(rest.coco17[0])) > 0.05


def test_onto_the_head_applies_to_a_single_photo_only():
    """One photo: its wrist on the head is moved to the head's depth before the bone term reads it. Two
    views: the landmarks are kept (the other view sees the depth; in an orbit's side views an arm held
    out towards the camera lies on the head across the image plane)."""
    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    from humanvdm_core.body.fit import FitOptions, FrameObservation, _Problem
    from humanvdm_core.cameras import orbit_cameras
    from testdata.synthetic import body_model

    world = np.zeros((17, 3), np.float32)
    world[0] = [0.0, -0.65, -0.2]
    world[[3, 4]] = [[0.07, -0.66, -0.1], [-0.07, -0.66, -0.1]]
    world[[5, 6, 11, 12]] = [[0.18, -0.5, 0.0], [-0.18, -0.5, 0.0], [0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    world[10] = [-0.08, -0.52, -0.45]  # the right palm on the cheek, taken 0.25 m before the nose
    px = np.tile(np.array([[128.0, 128.0]], np.float32), (17, 1)) + np.arange(17, dtype=np.float32)[:, None]

    def raw_wrist_z(views: int) -> list[float]:
        cams = orbit_cameras(views, 256, azimuths_deg=np.arange(views) * 30.0)
        obs = [FrameObservation(i, px, np.ones(17, np.float32), np.ones((32, 32), np.float32), [], world)
               for i in range(views)]
        return [float(z) for z in _Problem(body_model(), cams, obs, FitOptions()).raw_world[:, 10, 2]]

    assert raw_wrist_z(1) == pytest.approx([-0.15])
    assert raw_wrist_z(2) == pytest.approx([-0.45, -0.45])


def test_fit_smpl_warning_summary():
    warnings = [f"frame {i:04d}: keypoints unusable (too little of the body is visible in frame {i:04d}: left hip "
                "not visible)" for i in (3, 7, 10, 12, 15, 17, 19)]
    warnings += ["not clearly visible in frame 0004: left wrist, right ankle", "not clearly visible in frame 0005: "
                 "left wrist", "poor silhouette fit: mean IoU 0.70", "poor silhouette fit: mean IoU 0.70",
                 "odd in frame 0002", "odd in frame 0008", "odd in frame 0009"]
    lines = summarize_warnings(warnings, 21, {"0001": "no person found in frame 0001"})
    assert lines == [
        "frames skipped (no usable person): 1 of 21 frames (0001)",
        "keypoints unusable in 7 of 21 frames (0003, 0007, 0010, 0012, 0015, 0017, ...); only the silhouette "
        "was fitted there",
        "poor silhouette fit: mean IoU 0.70",
        "odd in frame *: 3 of 21 frames (0002, 0008, 0009)",
    ]
    assert summarize_warnings([], 21) == []
    # a joint hidden in most frames is a guess; one hidden in a few (an orbit's side views) is not
    hidden = [f"not clearly visible in frame {i:04d}: left wrist" + (", right elbow" if i < 3 else "")
              for i in range(11)]
    assert summarize_warnings(hidden, 21) == [
        "joints not clearly visible in most frames, so their pose is a guess: left wrist (hidden in 11 of 21)"]
    assert summarize_warnings(hidden[:10], 21) == []
    # ... unless the input photo's frame shows it: hands on the hips, hidden from the side and behind
    assert summarize_warnings(hidden, 21, seen_in="0020") == []
    assert summarize_warnings(hidden, 21, seen_in="0000") == [
        "joints not clearly visible in most frames, so their pose is a guess: left wrist (hidden in 11 of 21)"]
    assert summarize_warnings(["not clearly visible in frame 0000: left wrist, left elbow"], 1) == [
        "joints not clearly visible in most frames, so their pose is a guess: left elbow (hidden in 1 of 1), "
        "left wrist (hidden in 1 of 1)"]


def test_stage_params_match_fit_options():
    """fit-smpl's params default to FitOptions' defaults (the stage module does not import torch)."""
    from dataclasses import fields

    from humanvdm_core.body.fit import FitOptions
    from stages.fit_smpl import SPEC

    defaults = {f.name: f.default for f in fields(FitOptions)}
    shared = set(defaults) & set(SPEC.params)
    assert {"silhouette_cover_weight", "bone_direction_weight", "single_view_pose_prior_weight_3d"} <= shared
    for name in shared:
        assert SPEC.params[name].default == defaults[name], name


def test_a_body_inside_a_clothed_person_is_no_poor_fit_and_one_sticking_out_is():
    """A box "body" seen by one camera against three person masks: its own silhouette grown on every side
    (a coat: IoU under 0.75, which used to read "poor silhouette fit") raises no doubt; the same mask
    moved so a fifth of the body or more sticks out raises the poor fit; a mask grown until the body covers
    under 40 % of it (a ball gown) says how little the body covers."""
    import cv2
    import trimesh

    from humanvdm_core.body.fit import render_masks, silhouette_doubts, silhouette_scores
    from humanvdm_core.cameras import orbit_cameras

    torch.set_num_threads(1)
    box = trimesh.creation.box(extents=(0.4, 1.6, 0.3))
    cam = orbit_cameras(1, 128, 33.8, 0.0, 3.0, azimuths_deg=np.array([0.0]))
    own = render_masks(box.vertices, box.faces, cam)[0] > 0.5

    def grown(px: int) -> np.ndarray:
        return cv2.dilate(own.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(np.float32)

    coat = grown(4)
    moved = np.roll(grown(1), int(0.4 * np.nonzero(own.any(axis=0))[0].size), axis=1)
    gown = grown(20)
    scores = {name: silhouette_scores(box.vertices, box.faces, cam, [m]) for name, m in
              (("coat", coat), ("moved", moved), ("gown", gown))}
    iou, outside, cover = scores["coat"]
    assert iou[0] < 0.75 and outside[0] < 0.02 and silhouette_doubts(outside, cover) == []
    iou, outside, cover = scores["moved"]
    assert outside[0] > 0.2 and silhouette_doubts(outside, cover)[0].startswith("poor silhouette fit")
    iou, outside, cover = scores["gown"]
    doubts = silhouette_doubts(outside, cover)
    assert cover[0] < 0.4 and len(doubts) == 1 and "covers only" in doubts[0]


@pytest.mark.slow
def test_a_seated_person_photographed_from_the_side_keeps_level_thighs(photo, monkeypatch):
    """A seated person photographed 45 deg round to their right: their thighs point at the camera at a slant,
    and the detector reads those knees where they are, not low, so they are raised less or not at all
    (``KNEE_RAISE_FULL`` / ``KNEE_RAISE_NONE``); raised by the whole share, as for thighs that point at the
    camera, a knee came out above its hip and the knees and ankles 0.12 m from the true ones (0.08 now)."""
    import humanvdm_core.body.landmarks as landmarks

    obs, cam, truth, m = photo("seated-turned")

    def legs(c):  # the thighs' angles from straight down (deg), the knees' and ankles' offsets from the hips (m)
        down = np.array([0.0, -1.0, 0.0])
        hips = c[[11, 12]].mean(0)
        return (np.array([_angle_deg(c[k] - c[h], down) for h, k in ((11, 13), (12, 14))]), (c[13:17] - hips) * m)

    true, true_at = legs(truth)
    fitted, fitted_at = legs(_fit(obs, cam).output.coco17[0].numpy().astype(np.float64))
    monkeypatch.setattr(landmarks, "KNEE_RAISE_FULL", 10.0)  # every knee raised by the whole share
    monkeypatch.setattr(landmarks, "KNEE_RAISE_NONE", 11.0)
    whole, whole_at = legs(_fit(obs, cam).output.coco17[0].numpy().astype(np.float64))
    print(f"thighs from vertical: {fitted.round(1)} deg, {whole.round(1)} raised whole, true {true.round(1)}; "
          f"knees and ankles off by {np.linalg.norm(fitted_at - true_at, axis=1).round(3)} m, "
          f"{np.linalg.norm(whole_at - true_at, axis=1).round(3)} raised whole")
    assert np.all(np.abs(fitted - true) < 6.0) and np.all(fitted < 90.0), (fitted, true)
    assert np.max(whole) > 90.0, whole  # what the whole raise did: a knee above its hip
    off, off_whole = np.linalg.norm(fitted_at - true_at, axis=1).mean(), np.linalg.norm(whole_at - true_at, axis=1).mean()
    assert off < 0.09 and off_whole > off + 0.03, (off, off_whole)

