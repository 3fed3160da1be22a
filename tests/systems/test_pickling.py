"""Messages between a run's processes: CPU tensors pickled as NumPy arrays (``systems.pickling``)."""

import dataclasses
import pickle

import torch

from torchslam.fastgo import PairStats
from torchslam.systems.pickling import dumps, loads


def test_tensors_come_back_with_their_values_dtypes_and_shapes_in_memory_of_their_own():
    g = torch.Generator().manual_seed(0)
    base = torch.rand(5, 7, generator=g, dtype=torch.float64)
    obj = {
        "f32": torch.rand(3, 4, generator=g),
        "f64": base,
        "u8": torch.randint(0, 256, (6, 32), generator=g, dtype=torch.uint8),
        "i64": torch.arange(12).view(3, 4),
        "bool": torch.rand(9, generator=g) > 0.5,
        "scalar": torch.tensor(2.5),
        "empty": torch.zeros(0, 3),
        "transposed": base.t(),  # non-contiguous
        "slice": base[1:4, 2:],  # an offset view
        "again": base,  # the same object twice
        "nested": [(torch.eye(4, dtype=torch.float64), "pose")],
    }
    out = loads(dumps(obj))
    for key in ("f32", "f64", "u8", "i64", "bool", "scalar", "empty", "transposed", "slice"):
        assert out[key].dtype == obj[key].dtype and out[key].shape == obj[key].shape, key
        assert torch.equal(out[key], obj[key]), key
        assert out[key].untyped_storage().data_ptr() != obj[key].untyped_storage().data_ptr() or obj[key].numel() == 0
    assert out["again"] is out["f64"]
    assert torch.equal(out["nested"][0][0], torch.eye(4, dtype=torch.float64)) and out["nested"][0][1] == "pose"
    out["f64"][0, 0] = -1.0  # writable, and the input keeps its values
    assert base[0, 0] != -1.0
    # A view travels as the elements it shows, not its whole storage.
    big = torch.zeros(1000, 1000)
    assert len(dumps(big[:2, :2])) < 1000 < len(pickle.dumps(big[:2, :2]))


def test_what_numpy_cannot_hold_is_pickled_as_pickle_would():
    half = torch.rand(4, 3).to(torch.bfloat16)
    param = torch.nn.Parameter(torch.rand(2, 2))
    grad = torch.rand(3, requires_grad=True)
    out = loads(dumps({"bf16": half, "param": param, "grad": grad, "text": "x"}))
    assert out["bf16"].dtype == torch.bfloat16 and torch.equal(out["bf16"], half)
    assert isinstance(out["param"], torch.nn.Parameter) and torch.equal(out["param"].data, param.data)
    assert out["grad"].requires_grad and torch.equal(out["grad"].detach(), grad.detach())
    assert out["text"] == "x"


def test_pair_statistics_travel_whole():
    g = torch.Generator().manual_seed(1)
    p_i = torch.rand(1, 50, 3, generator=g, dtype=torch.float64)
    stats = PairStats.from_padded(p_i, p_i + 0.01, mask=torch.ones(1, 50, dtype=torch.bool))
    back = loads(dumps(stats))
    names = [f.name for f in dataclasses.fields(stats)]
    assert {"n", "count", "s_i", "S_ij"} <= set(names)
    for name in names:
        assert torch.equal(getattr(back, name), getattr(stats, name)), name
