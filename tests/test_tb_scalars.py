"""benchmarks/tb_scalars.py: windowed means of logged scalars."""

import pytest

from benchmarks.tb_scalars import main, windowed_means


def test_windowed_means_groups_by_window_in_step_order():
    points = [(0, 1.0), (99, 3.0), (100, 10.0), (250, 4.0), (260, 6.0)]
    assert windowed_means(points, 100) == [(0, 2.0, 2), (100, 10.0, 1), (200, 5.0, 2)]


def test_windowed_means_rejects_a_window_of_zero():
    with pytest.raises(ValueError, match="window"):
        windowed_means([(0, 1.0)], 0)


def test_main_reads_events_written_by_a_summary_writer(tmp_path, capsys):
    tb = pytest.importorskip("torch.utils.tensorboard")
    writer = tb.SummaryWriter(str(tmp_path / "run"))
    for step in range(0, 400, 10):
        writer.add_scalar("Train Metrics Dict/psnr", 20.0 if step < 200 else 10.0, step)
        writer.add_scalar("Train Loss", 1.0, step)
    writer.close()
    main([str(tmp_path), "--tags", "psnr", "--window", "200"])
    out = capsys.readouterr().out
    assert "Train Metrics Dict/psnr: 0:20 200:10" in out
    assert "Train Loss" not in out


def test_main_says_when_there_is_no_events_file(tmp_path):
    with pytest.raises(SystemExit, match="no events file"):
        main([str(tmp_path)])
