"""ORB features (OpenCV) as tensors and Hamming-distance matching of binary descriptors."""

from .matching import (
    BatchedMatches,
    HammingKernel,
    MatchBackend,
    Matches,
    hamming_distance,
    hamming_distance_indexed,
    hamming_distance_packed,
    match_descriptors,
    match_descriptors_batched,
    pack_descriptors,
    pad_descriptors,
    popcount64,
)
from .orb import DESCRIPTOR_BYTES, Features, ORBConfig, ORBScore, extract_orb, rgb_to_grey_u8

__all__ = [
    "BatchedMatches",
    "DESCRIPTOR_BYTES",
    "Features",
    "HammingKernel",
    "MatchBackend",
    "Matches",
    "ORBConfig",
    "ORBScore",
    "extract_orb",
    "hamming_distance",
    "hamming_distance_indexed",
    "hamming_distance_packed",
    "match_descriptors",
    "match_descriptors_batched",
    "pack_descriptors",
    "pad_descriptors",
    "popcount64",
    "rgb_to_grey_u8",
]
