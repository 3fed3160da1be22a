"""torchslam: batched, tensorised RGB-D SLAM in PyTorch (GC-SLAM with FastGO, NI-SLAM with KCC)."""

__version__ = "0.1.0"
