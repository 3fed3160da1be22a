"""Live monitoring of a run: ATE so far, running stage times, counters, trajectory image."""

import pytest
import torch

from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.data import Sequence
from torchslam.systems import SlamSystem, run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig
from torchslam.systems.monitor import Monitor
from torchslam.app.progress import log_final, progress_callback


class Recorder(Monitor):
    def __init__(self):
        self.scalars_, self.images = {}, {}

    def scalar(self, tag, value, step):
        self.scalars_.setdefault(tag, []).append((step, float(value)))

    def image(self, tag, image, step):
        self.images[tag] = (step, image)


def test_progress_logs_ate_so_far_stage_times_counters_and_trajectory_image():
    seq = generate_sequence(SyntheticConfig(frames=30, width=320, height=240, trajectory="orbit", seed=5))
    mon = Recorder()
    system = GCSlam(GCSlamConfig(threaded=False), monitor=mon)
    sizes = []
    hook = progress_callback(system, seq, mon, every=10)

    def on_frame(n):
        sizes.append(len(system.estimate_so_far()))
        hook(n)

    result = run_sequence(system, seq, on_frame=on_frame)
    # Synchronous optimisation: every frame processed so far has a pose.
    assert sizes == list(range(1, 31))
    # The step is the frame index: frames 9, 19 and 29 are the 10th, 20th and 30th.
    ate_steps = [s for s, _ in mon.scalars_["eval/ate_so_far_m"]]
    assert ate_steps == [9, 19, 29]
    assert all(0 <= v < 0.01 for _, v in mon.scalars_["eval/ate_so_far_m"])
    assert [s for s, _ in mon.scalars_["timing/registration_ms"]] == [9, 19, 29]
    assert mon.scalars_["progress/keyframes"][-1][1] == len(system.keyframes)
    # GC-SLAM logs each new keyframe under the same tag as NI-SLAM, at the keyframe's frame index.
    assert "tracking/keyframes" not in mon.scalars_ and mon.scalars_["progress/keyframes"][0] == (0, 1.0)
    # FastGO runs for the keyframes with loop candidates (fastgo_every_keyframe off), at their frame index.
    fastgo_steps = [s for s, _ in mon.scalars_["optimization/fastgo_ms"]]
    assert fastgo_steps and set(fastgo_steps) <= {int(k.frame_index) for k in system.keyframes[1:]}
    assert fastgo_steps == sorted(fastgo_steps)
    # Running mean per frame: the last one equals the stage total over 30 frames.
    assert abs(mon.scalars_["timing/registration_ms"][-1][1] - system.stage_ms["registration"] / 30) < 1e-9

    log_final(mon, result.output, seq, "orbit")
    step, img = mon.images["trajectory/top_view"]
    assert step == 29 and img.dim() == 3 and img.shape[0] == 3 and img.shape[1] > 100
    assert float(img.min()) >= 0 and float(img.max()) <= 1 and float(img.std()) > 0.01


def test_progress_without_groundtruth_or_estimate_logs_only_what_exists():
    # Only what the protocols require: the optional capabilities keep their defaults.
    class Plain(SlamSystem):
        stage_ms = {"work": 5.0}

    class NoTruth(Sequence):
        groundtruth = None

    mon = Recorder()
    hook = progress_callback(Plain(), NoTruth(), mon, every=1)
    hook(1)
    hook(2)
    assert "eval/ate_so_far_m" not in mon.scalars_
    assert mon.scalars_["timing/work_ms"] == [(0, 5.0), (1, 2.5)]


def test_estimate_so_far_after_the_last_frame_equals_the_final_trajectory():
    # Without a final re-optimisation and with depth instants equal to the frame stamps, the
    # live estimate after the last frame is the output.
    from torchslam.systems.nislam import NISlam

    seq = generate_sequence(SyntheticConfig(frames=24, width=320, height=240, trajectory="orbit", seed=6))
    for system in (NISlam(), GCSlam(GCSlamConfig(threaded=False, final_iterations=0))):
        live = []
        result = run_sequence(system, seq, on_frame=lambda n, s=system: live.append(s.estimate_so_far()) if n == len(seq) else None)
        out = result.output
        torch.testing.assert_close(live[0].T_wc, out.T_wc, rtol=0, atol=1e-12)
        torch.testing.assert_close(live[0].timestamps, out.timestamps, rtol=0, atol=0)


def test_tensorboard_tags_and_steps_of_a_short_nislam_run(tmp_path):
    """The event file of a run holds one tag scheme, frame-index steps and the response image."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from torchslam.app.run import RunOptions, run

    out = tmp_path / "run"
    opts = RunOptions(system="nislam", data="synthetic", out=out, monitor_every=5)
    run(opts, overrides=["data.synthetic.frames=16", "data.synthetic.width=160", "data.synthetic.height=120",
                         "data.synthetic.trajectory=translate"])
    acc = EventAccumulator(str(out), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    scalars, images = set(acc.Tags()["scalars"]), set(acc.Tags()["images"])
    assert {"eval/ate_so_far_m", "progress/keyframes", "tracking/psr", "timing/kcc_ms"} <= scalars
    assert not any(t.startswith("map/") for t in scalars)  # the old NI-SLAM-only scheme
    assert {"keyframe/ortho_grey", "keyframe/response", "trajectory/top_view"} <= images
    assert [e.step for e in acc.Scalars("eval/ate_so_far_m")] == [4, 9, 14]
    assert [e.step for e in acc.Scalars("tracking/psr")] == list(range(1, 16))  # frame 0 is the first keyframe
    assert acc.Scalars("progress/keyframes")[0].step == 0
    assert [e.step for e in acc.Images("keyframe/response")] == [1]  # the first frame matched against keyframe 0
    assert acc.Images("trajectory/top_view")[0].step == 15
