import numpy as np

from mosaic.posegraph import Constraint, refine_poses
from mosaic.tracking import corners, project
from tests.helpers import similarity

SHAPE = (300, 400)


def _corner_error(H_a, H_b):
    return float(
        np.linalg.norm(project(H_a, corners(SHAPE)) - project(H_b, corners(SHAPE)), axis=1).mean()
    )


def test_pose_graph_recovers_poses_from_noisy_constraints():
    rng = np.random.default_rng(0)
    n = 8
    # A loop: keyframes on a circle, each rotated a little.
    truth = {
        k: similarity(
            3.0 * np.sin(k),
            1.0 + 0.02 * np.cos(k),
            150 * np.cos(2 * np.pi * k / n),
            150 * np.sin(2 * np.pi * k / n),
        )
        for k in range(n)
    }
    truth = {k: np.linalg.inv(truth[0]) @ H for k, H in truth.items()}  # keyframe 0 = reference
    pairs = [(k, k + 1) for k in range(n - 1)] + [(n - 1, 0), (4, 0)]
    constraints = []
    grid = np.stack(np.meshgrid(np.linspace(20, 380, 6), np.linspace(20, 280, 5)), -1).reshape(
        -1, 2
    )
    for a, b in pairs:
        xy_b = project(np.linalg.inv(truth[b]) @ truth[a], grid) + rng.normal(0, 0.5, grid.shape)
        constraints.append(Constraint(a, b, grid, xy_b))
    # Initial poses drift: each keyframe is off by an error that grows along the chain.
    initial = {k: H.copy() for k, H in truth.items()}
    for k in range(1, n):
        initial[k][:2, 2] += [4.0 * k, -3.0 * k]
        initial[k][:2, :2] *= 1 + 0.004 * k
    before = np.mean([_corner_error(initial[k], truth[k]) for k in range(1, n)])
    result = refine_poses(initial, constraints, fixed=0)
    after = np.mean([_corner_error(result.poses[k], truth[k]) for k in range(1, n)])
    assert before > 15.0
    assert after < before / 10, (before, after)
    assert after < 1.0
    assert result.rms_after_px < result.rms_before_px
    assert result.rms_after_px < 1.0  # noise is 0.5 px per coordinate
    np.testing.assert_array_equal(result.poses[0], initial[0])


def test_a_wrong_loop_closure_is_dropped():
    truth = {k: similarity(0, 1, 100.0 * k, 0) for k in range(4)}
    grid = np.stack(np.meshgrid(np.linspace(20, 380, 5), np.linspace(20, 280, 4)), -1).reshape(
        -1, 2
    )
    constraints = [
        Constraint(a, a + 1, grid, project(np.linalg.inv(truth[a + 1]) @ truth[a], grid))
        for a in range(3)
    ]
    # A bogus closure claiming keyframe 3 sits 60 px from where it is.
    constraints.append(
        Constraint(3, 0, grid, project(truth[3], grid) + np.array([60.0, 0.0]), loop=True)
    )
    result = refine_poses(truth, constraints, fixed=0)
    assert result.dropped_loops == 1
    assert _corner_error(result.poses[3], truth[3]) < 0.1
