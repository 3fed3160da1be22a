"""``TensorBoardMonitor``: events at the first record; without TensorBoard, nothing recorded and one warning."""

from __future__ import annotations

import logging
import sys

import torch

from torchslam.systems.monitor import TensorBoardMonitor


def test_the_event_file_is_made_at_the_first_record(tmp_path):
    # A run that fails before recording anything leaves no half-made folder behind.
    m = TensorBoardMonitor(tmp_path / "tb")
    assert not (tmp_path / "tb").exists()
    m.scalar("a", 1.0, 0)
    m.image("b", torch.zeros(3, 4, 4), 0)
    m.close()
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))


def test_without_tensorboard_the_monitor_records_nothing_and_says_so_once(tmp_path, monkeypatch, caplog):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails
    m = TensorBoardMonitor(tmp_path / "tb")
    with caplog.at_level(logging.WARNING, logger="torchslam.systems.monitor"):
        m.scalar("a", 1.0, 0)
        m.scalar("a", 2.0, 1)
        m.image("b", torch.zeros(1, 2, 2), 0)
        m.hparams({"x": 1}, {"ate": 0.1})
        m.close()
    assert sum("TensorBoard events not written" in r.message for r in caplog.records) == 1
    assert not (tmp_path / "tb").exists()
