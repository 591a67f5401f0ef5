import numpy as np
import pytest

from tambridge.errors import TrajectoryFormatError
from tambridge.evaluation.trajectory import ate_rmse_m, evaluate_trajectory
from tambridge.geometry import exp_se3, interpolate_pose, poses_along
from tambridge.io.synthetic import loop_path
from tambridge.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory


def _reference(count=50) -> Trajectory:
    return Trajectory(np.arange(count) / 30.0, loop_path(count))


def test_tum_round_trip(tmp_path):
    reference = _reference()
    write_tum_trajectory(tmp_path / "t.txt", reference)
    loaded = read_tum_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(loaded.timestamps_s, reference.timestamps_s, atol=1e-6)
    np.testing.assert_allclose(loaded.world_from_camera, reference.world_from_camera, atol=1e-8)


def test_ate_of_a_known_perturbation_equals_its_rms():
    reference = _reference()
    rng = np.random.default_rng(3)
    offsets = rng.normal(0.0, 0.02, size=(len(reference), 3))
    offsets -= offsets.mean(axis=0)  # a zero-mean perturbation is not absorbed by alignment's translation
    perturbed = reference.world_from_camera.copy()
    perturbed[:, :3, 3] += offsets
    expected = np.sqrt(np.mean(np.sum(offsets**2, axis=1)))
    estimate = Trajectory(reference.timestamps_s, perturbed)
    assert ate_rmse_m(estimate, reference, align="none") == pytest.approx(expected, rel=1e-9)
    # A rigid motion of the whole estimate is removed by SE(3) alignment (up to the noise it can fit).
    moved = Trajectory(reference.timestamps_s, exp_se3(np.array([1.0, -2.0, 0.5, 0.3, -0.2, 1.0])) @ perturbed)
    assert ate_rmse_m(moved, reference, align="none") > 0.5
    assert ate_rmse_m(moved, reference, align="se3") == pytest.approx(expected, rel=0.05)


def test_sim3_alignment_recovers_a_known_scale():
    reference = _reference()
    scaled = reference.world_from_camera.copy()
    scaled[:, :3, 3] *= 0.37
    moved = exp_se3(np.array([0.2, 0.1, -0.4, 0.5, 0.0, -0.3])) @ scaled
    errors = evaluate_trajectory(Trajectory(reference.timestamps_s, moved), reference, align="sim3")
    assert errors.scale == pytest.approx(1 / 0.37, rel=1e-6)
    assert errors.ate_rmse_m < 1e-9
    assert evaluate_trajectory(Trajectory(reference.timestamps_s, moved), reference, align="se3").ate_rmse_m > 0.05


def test_rpe_of_a_constant_step_error():
    reference = _reference()
    drifted = reference.world_from_camera.copy()
    # Each relative motion gains 1 mm along the camera x axis: RPE is exactly 1 mm per frame.
    relative = [np.linalg.inv(a) @ b for a, b in zip(reference.world_from_camera[:-1], reference.world_from_camera[1:])]
    step_error = np.eye(4)
    step_error[0, 3] = 0.001
    for index, motion in enumerate(relative, start=1):
        drifted[index] = drifted[index - 1] @ motion @ step_error
    errors = evaluate_trajectory(Trajectory(reference.timestamps_s, drifted), reference, align="none")
    assert errors.rpe_trans_rmse_m == pytest.approx(0.001, rel=1e-6)


def test_association_skips_poses_without_a_partner():
    reference = _reference()
    estimate = Trajectory(reference.timestamps_s[::2] + 0.004, reference.world_from_camera[::2])
    errors = evaluate_trajectory(estimate, reference, align="none")
    assert errors.pose_count == len(reference.timestamps_s[::2])
    assert errors.ate_rmse_m < 1e-9


@pytest.mark.parametrize(
    "text, message",
    [
        ("1.0 0 0 0 0 0 0\n", "line 1: expected 8 columns"),
        ("1.0 0 0 0 0 0 0 x\n", "line 1: 'x' is not a number; a TUM line holds 8 numbers"),
        ("# only a comment\n", "no poses"),
        ("1.0 0 0 0 0 0 0 0\n", "line 1: quaternion qx qy qz qw has norm 0, not 1; the columns must be"),
        # Columns swapped (qw first, then a position): the norm gives it away.
        ("1.0 0 0 0 1 0.5 0.2 0.3\n", "line 1: quaternion qx qy qz qw has norm 1.175, not 1"),
        ("1.0 0 0 0 1e300 1e300 0 0\n", "line 1: quaternion qx qy qz qw has norm too large to square, not 1"),
        ("1.0 nan 0 0 0 0 0 1\n", "line 1: non-finite value \\(nan or inf\\); fix or remove the line"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.0 0 0 0.5 0 0 0 1\n",
         "line 3: time 1.0 is already on line 1 with another pose; list each time once"),
    ],
)
def test_malformed_trajectory_files_name_the_line(tmp_path, text, message):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryFormatError, match=message):
        read_tum_trajectory(path)


def test_a_folder_given_as_a_trajectory_is_named_with_the_file_inside(tmp_path):
    with pytest.raises(TrajectoryFormatError, match=rf"^{tmp_path}: is a folder; pass a TUM trajectory file$"):
        read_tum_trajectory(tmp_path)
    (tmp_path / "trajectory.txt").write_text("1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=rf"is a folder; pass a TUM trajectory file \({tmp_path}/trajectory\.txt, say\)$"):
        read_tum_trajectory(tmp_path)


def test_a_time_repeated_with_its_pose_is_read_once_and_rounded_quaternions_are_normalised(tmp_path):
    path = tmp_path / "repeated.txt"
    # TUM's 4-decimal quaternions are unit to about 2e-4 only; 0.7071 twice has norm 0.99999.
    path.write_text("2.0 1 2 3 0 0 0.7071 0.7071\n1.0 0 0 0 0 0 0 1\n2.0 1 2 3 0 0 0.7071 0.7071\n")
    trajectory = read_tum_trajectory(path)
    np.testing.assert_array_equal(trajectory.timestamps_s, [1.0, 2.0])
    np.testing.assert_allclose(trajectory.world_from_camera[1][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_nearest_poses_match_a_search_over_every_pose():
    rng = np.random.default_rng(11)
    reference = Trajectory(np.sort(rng.uniform(0.0, 10.0, 60)), loop_path(60))
    queries = np.concatenate([rng.uniform(-1.0, 11.0, 200), reference.timestamps_s[::7],
                              # halfway between two poses: the earlier one
                              (reference.timestamps_s[:-1:5] + reference.timestamps_s[1::5]) / 2])
    rows = [int(np.argmin(np.abs(reference.timestamps_s - stamp))) for stamp in queries]
    picked = reference.nearest(queries)
    np.testing.assert_array_equal(picked.timestamps_s, reference.timestamps_s[rows])
    np.testing.assert_array_equal(picked.world_from_camera, reference.world_from_camera[rows])
    single = Trajectory(reference.timestamps_s[:1], reference.world_from_camera[:1])
    assert len(single.nearest(queries[:5])) == 5


def test_too_few_poses_or_none_on_the_clock_are_told_apart():
    from tambridge.errors import TrajectoryEvaluationError

    poses = loop_path(10)
    truth = Trajectory(np.arange(10) / 30.0, poses)
    with pytest.raises(TrajectoryEvaluationError, match=r"^the estimate has 2 poses; ATE needs at least 3"):
        evaluate_trajectory(Trajectory(truth.timestamps_s[:2], poses[:2]), truth)
    with pytest.raises(TrajectoryEvaluationError, match=r"^only 0 of 10 estimated poses lie within 0.02 s"):
        evaluate_trajectory(Trajectory(truth.timestamps_s + 100.0, poses), truth)


def test_bridged_moves_unlocalised_poses_onto_the_geodesic_between_their_neighbours():
    reference = _reference(40)
    localised = np.ones(40, bool)
    localised[[0, 1, 10, 11, 12, 25, 39]] = False
    rng = np.random.default_rng(3)
    garbage = reference.world_from_camera.copy()
    garbage[~localised] = np.stack([exp_se3(rng.normal(0.0, 0.5, 6)) for _ in range(int((~localised).sum()))])
    bridged = Trajectory(reference.timestamps_s, garbage).bridged(localised)

    # Before the first and after the last localised pose nothing can bridge: those stay as they were.
    for row in (0, 1, 39):
        np.testing.assert_array_equal(bridged.world_from_camera[row], garbage[row])
    np.testing.assert_array_equal(bridged.world_from_camera[localised], reference.world_from_camera[localised])
    # The three-frame gap 10-12 lies between poses 9 and 13, at a quarter, half and three quarters of the way.
    start, end = reference.world_from_camera[9], reference.world_from_camera[13]
    for row, fraction in ((10, 0.25), (11, 0.5), (12, 0.75)):
        np.testing.assert_allclose(bridged.world_from_camera[row], interpolate_pose(start, end, fraction), atol=1e-9)
    np.testing.assert_allclose(bridged.world_from_camera[25], interpolate_pose(reference.world_from_camera[24],
                                                                               reference.world_from_camera[26], 0.5), atol=1e-9)
    # On the curving loop the constant-velocity prediction from before the gap runs off as the gap goes on; the
    # geodesic's largest error over the gap is under half of the prediction's.
    times, poses = reference.timestamps_s, reference.world_from_camera
    predicted = poses_along(times[[8, 9]], poses[[8, 9]], times[[10, 11, 12]])[:, :3, 3]
    bridged_error = np.linalg.norm(bridged.positions_m[[10, 11, 12]] - reference.positions_m[[10, 11, 12]], axis=1)
    predicted_error = np.linalg.norm(predicted - reference.positions_m[[10, 11, 12]], axis=1)
    assert bridged_error.max() < 0.5 * predicted_error.max(), (bridged_error, predicted_error)
    assert len(Trajectory(reference.timestamps_s[:1], garbage[:1]).bridged(np.zeros(1, bool))) == 1
