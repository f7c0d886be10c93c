"""ELOPE velocity score (eq. 18–19) and the challenge's submission JSON."""

import json

import numpy as np
import pytest
from evgs.eval.elope import (
    elope_errors,
    elope_score,
    sequence_id,
    submission_velocities,
    velocities,
    write_submission,
)

T = np.array([0.0, 1.0, 2.0, 4.0])
P_GT = np.array([[0.0, 0, -100], [1, 0, -100], [2, 0, -50], [2, 0, -40]])
P_EST = np.array([[0.0, 0, -100], [1, 1, -100], [2, 1, -50], [2, 4, -40]])


def test_velocities_first_differences():
    np.testing.assert_allclose(velocities(T, P_GT), [[1, 0, 0], [1, 0, 50], [0, 0, 5]])
    with pytest.raises(ValueError, match="strictly increasing"):
        velocities(np.array([0.0, 1.0, 1.0]), P_GT[:3])


def test_score_hand_computed_uses_abs_altitude():
    # v_est − v_gt: (0, 1, 0), (0, 0, 0), (0, 1.5, 0); |z_gt| at the interval starts: 100, 100, 50.
    np.testing.assert_allclose(elope_errors(T, P_EST, P_GT), [0.01, 0.0, 0.03])
    assert elope_score(T, P_EST, P_GT) == pytest.approx((0.01 + 0.0 + 0.03) / 3)
    # Flipping the sign convention of z (negative altitude) changes nothing.
    flip = np.array([1.0, 1.0, -1.0])
    assert elope_score(T, P_EST * flip, P_GT * flip) == pytest.approx(elope_score(T, P_EST, P_GT))


def test_submission_format(tmp_path):
    v = submission_velocities(T, P_EST)
    assert v.shape == (4, 3)  # one value per timestamp; the last repeats the last interval
    np.testing.assert_allclose(v[-1], v[-2])
    write_submission(tmp_path / "sub.json", {sequence_id("elope_0028"): v, sequence_id("0029"): v})
    doc = json.loads((tmp_path / "sub.json").read_text())
    assert list(doc) == ["28", "29"]
    assert set(doc["28"]) == {"vx", "vy", "vz"}
    np.testing.assert_allclose(doc["28"]["vy"], v[:, 1])
    bad = v.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="row 2"):
        write_submission(tmp_path / "bad.json", {"1": bad})
    assert not (tmp_path / "bad.json").exists()
    with pytest.raises(ValueError):
        sequence_id("orbit_ambient")
