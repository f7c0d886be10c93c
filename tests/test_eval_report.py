"""Run evaluation, figures, reports, exports and the ``evgs eval`` command on small fake runs."""

import json

import numpy as np
import polars as pl
import pytest
from eval_synth import fake_run
from evgs.cli import main
from evgs.data.tum import read_tum
from evgs.eval.plots import plot_run
from evgs.eval.report import write_report
from evgs.eval.run import evaluate_run, frame_indices


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    rng = np.random.default_rng(7)
    return [
        fake_run(root, "orbit_a", rng),
        fake_run(root, "elope_0003", rng, source="ELOPE", z_offset=-50.0),
    ]


def test_evaluate_run_metrics_and_notes(runs):
    ev = evaluate_run(runs[0])
    assert ev.frame_range == "0-29"
    assert ev.assoc.dropped == 0
    assert 0 < ev.traj.ate_rmse < 0.05  # 1 cm noise per axis, Sim(3) removed
    assert ev.elope_score is None  # not an ELOPE sequence
    assert ev.images is None
    assert any("gaussians.ply" in n for n in ev.notes)  # the skip is reported, not silent
    assert evaluate_run(runs[1], images=False).elope_score is not None


def test_frame_indices():
    frames = np.array([0, 100, 200], np.int64)
    np.testing.assert_array_equal(frame_indices(np.array([0.0, 101e-6, 150e-6, 2e-4]), frames), [0, 1, -1, 2])


def test_figures_and_self_contained_html(runs, tmp_path):
    ev = evaluate_run(runs[0], images=False)
    (runs[0] / "metrics.json").write_text(json.dumps({"frames_tracked": 30, "loss": 0.125, "curve": [1, 2]}))
    figs = plot_run(ev, tmp_path / "eval")
    assert set(figs) == {"trajectory", "translation", "rpy", "orientation_error", "velocity"}
    for p in figs.values():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    md, page = write_report(ev, figs, tmp_path)
    text = md.read_text()
    assert "| Sequence | Frames | RMSE | Drift | PSNR | LPIPS |" in text
    assert "](eval/trajectory_3d.png)" in text
    assert "| frames_tracked | 30 |" in text and "| loss | 0.125 |" in text and "curve" not in text
    html = page.read_text()
    assert html.count("src='data:image/png;base64,") == 5
    assert "http" not in html and "<link" not in html and "src='eval/" not in html


def test_cli_several_runs_table_csv_exports(runs, tmp_path, capsys):
    csv, exp, sub = tmp_path / "cmp.csv", tmp_path / "exp", tmp_path / "sub.json"
    exports = ["--export-tum", str(exp), "--export-kitti", str(exp), "--elope-submission", str(sub)]
    rc = main(["eval", *map(str, runs), "--csv", str(csv), *exports])
    assert rc == 0
    out = capsys.readouterr().out
    assert "orbit_a/20260101-000000" in out and "ate_rmse" in out
    table = pl.read_csv(csv)
    assert table.height == 2
    for run, row in zip(runs, table.iter_rows(named=True), strict=True):
        assert (run / "report.md").is_file() and (run / "report.html").is_file()
        metrics = json.loads((run / "eval" / "metrics.json").read_text())
        assert row["ate_rmse"] == pytest.approx(metrics["ate_rmse"])
        assert row["ate_rmse"] == pytest.approx(evaluate_run(run, images=False).traj.ate_rmse)
    # Exported aligned estimate = GT up to the noise; KITTI rows are the same poses' 3×4 matrices.
    t, T_est = read_tum(exp / "orbit_a_20260101-000000.est.tum")
    _, T_gt = read_tum(exp / "orbit_a_20260101-000000.gt.tum")
    kitti = np.loadtxt(exp / "orbit_a_20260101-000000.est.kitti")
    assert kitti.shape == (30, 12)
    np.testing.assert_allclose(kitti.reshape(-1, 3, 4), T_est[:, :3, :], atol=1e-8)
    assert np.sqrt(np.mean(np.sum((T_est[:, :3, 3] - T_gt[:, :3, 3]) ** 2, 1))) == pytest.approx(
        table["ate_rmse"][0], abs=1e-8
    )
    doc = json.loads(sub.read_text())
    assert list(doc) == ["3"] and len(doc["3"]["vz"]) == 30  # only the ELOPE run, one value per pose


def test_cli_reports_bad_input(runs, tmp_path, capsys):
    assert main(["eval", str(tmp_path)]) == 2
    assert "no config.toml" in capsys.readouterr().err
    sub = tmp_path / "sub.json"
    assert main(["eval", str(runs[0]), "--no-report", "--elope-submission", str(sub)]) == 2
    assert "none of the runs is an ELOPE run" in capsys.readouterr().err
    assert not sub.exists()


def test_unsorted_estimate_is_rejected_with_file_and_pose(runs, tmp_path):
    import shutil

    run = tmp_path / "r" / "x"
    shutil.copytree(runs[0], run)
    lines = (run / "traj_est.txt").read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]  # poses 3 and 4 (after the header line) swapped
    (run / "traj_est.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"traj_est.txt: pose 4: timestamps must be strictly increasing"):
        evaluate_run(run, images=False)
