"""GC-SLAM's front-ends: how a frame is prepared and registered to its keyframe (paper §IV-A).

Both front-ends have one interface, so the tracker never asks which one it runs:

* :meth:`TrackingFrontend.prepare` turns a frame's images into a :class:`PreparedFrame`: ORB
  features where the front-end needs them now, the dense pyramid for the dense front-end;
* :meth:`TrackingFrontend.register` registers a prepared frame to a keyframe and returns a
  :class:`Registration` (relative pose, FastGO statistics, correspondence count);
* :meth:`TrackingFrontend.features` computes a frame's ORB features when something else needs
  them (a new keyframe for MILD and loop registration, relocalisation).

The sparse front-end (:class:`SparseFrontend`) registers ORB features (isometry filter, RANSAC,
refinement); the dense one (:class:`DenseFrontend`) aligns the frame's pyramid to the current
keyframe's photometrically and geometrically, starting from the last frame's pose, and computes
ORB features only for keyframes.

Convention:
    ``T_kf`` (4, 4) float64 maps frame points into the keyframe: ``p_kf = T_kf p_frame``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol

import torch
from torch import Tensor

from ...fastgo import PairStats
from ...geometry import PinholeCamera, undistorted_rays
from ...registration.dense import DenseFrame, DenseResult, prepare_dense_frame, register_dense_frames
from ...registration.depth_align import refine_with_depth, sample_depth_points
from ...registration.rolling import correct_rows, dense_frame_at_stamp, features_at_stamp
from ...registration.sparse import FrameFeatures, SparseResult, frame_features, register_sparse, register_sparse_batch
from ..memory import DENSE_BYTES_PER_WORKING_PIXEL
from .config import Frontend, GCSlamConfig

__all__ = [
    "DenseFrontend",
    "PreparedFrame",
    "Registration",
    "RegistrationTarget",
    "SparseFrontend",
    "TrackingFrontend",
    "dense_working_pixels",
    "frontend_class",
    "make_frontend",
]


@dataclass
class PreparedFrame:
    """One frame as the front-end works on it.

    Attributes:
        rgb: (3, H, W) colour in [0, 1] on the tracker's device.
        depth: (1, H, W) depth, metres (0 = invalid).
        features: ORB features, or None until something needs them.
        dense: the dense pyramid (dense front-end only), else None.
        twist: (6,) float64 the camera's motion at the frame, per second (translation first, in
            its own coordinates), once the tracker has an estimate: what ``readout_time``'s
            rolling-shutter model moves the frame's pixels with; None before.
        moved: the twist the frame's registered points were moved to its stamp with
            (:meth:`TrackingFrontend.to_stamp`), None while they are as read.
        features_as_read: the ORB features before the sparse front-end moved them, else None.
    """

    rgb: Tensor
    depth: Tensor
    features: FrameFeatures | None = None
    dense: DenseFrame | None = None
    twist: Tensor | None = None
    moved: Tensor | None = None
    features_as_read: FrameFeatures | None = None


class RegistrationTarget(Protocol):
    """What a front-end registers a frame against: the keyframe's features and dense pyramid."""

    features: FrameFeatures
    dense: DenseFrame | None
    depth: Tensor | None
    # Optional: the motion its points or images were moved to its stamp with (readout_time); a
    # target without it, or with None, is taken as read.
    twist: Tensor | None


@dataclass(frozen=True)
class Registration:
    """A frame registered to its keyframe.

    Attributes:
        ok: the registration succeeded (enough inliers or correspondences).
        T_kf: (4, 4) float64 frame pose in the keyframe, ``p_kf = T_kf p_frame``.
        result: the registration of the pair (a batch of one; its ``stats`` are read on first use).
        correspondences: inliers (sparse) or correspondences (dense) kept.
    """

    ok: bool
    T_kf: Tensor
    result: SparseResult | DenseResult
    correspondences: int

    @property
    def stats(self) -> PairStats:
        """FastGO statistics of its correspondences (one pair; points in keyframe and frame). A
        dense result computes them on first read and keeps them: only a frame that becomes a
        keyframe needs them."""
        return self.result.stats


class TrackingFrontend:
    """The interface of both front-ends and their shared ORB extraction."""

    kind: ClassVar[Frontend]

    @property
    def uses_keyframe_depth(self) -> bool:
        """Whether registrations read the keyframe's depth image (``RegistrationTarget.depth``)."""
        return False

    def __init__(self, cfg: GCSlamConfig, camera: PinholeCamera, rays: Tensor | None, generator: torch.Generator,
                 readout: float = 0.0) -> None:
        """
        Args:
            cfg: GC-SLAM settings.
            camera: the sequence's camera.
            rays: (H*W, 2) undistorted normalised rays (:func:`~torchslam.geometry.undistorted_rays`)
                of a camera with distortion, else None.
            generator: the tracker's source of RANSAC seeds (shared with relocalisation).
            readout: the sequence's rolling-shutter readout, seconds (``readout_time`` resolved).
        """
        self.cfg = cfg
        self.camera = camera
        self.rays = rays
        self.generator = generator
        self.readout = readout
        self.orb_cfg = cfg.orb()

    def features(self, frame: PreparedFrame) -> FrameFeatures:
        """The frame's ORB features, computed on first use and kept in ``frame``."""
        if frame.features is None:
            frame.features = frame_features(frame.rgb, frame.depth, self.camera, self.orb_cfg, self.cfg.sparse, rays=self.rays)
        return frame.features

    def prepare(self, rgb: Tensor, depth: Tensor, keyframe: bool, lap: Callable[[str], None]) -> PreparedFrame:
        """Prepare a frame for registration.

        Args:
            rgb: (3, H, W) colour in [0, 1] on the tracker's device.
            depth: (1, H, W) depth, metres.
            keyframe: the frame becomes a keyframe whatever it registers to (its ORB features are
                needed).
            lap: called with a stage name when that stage of the preparation is done (timing).
        """
        raise NotImplementedError

    def register(self, keyframe: RegistrationTarget, frame: PreparedFrame, T_guess: Tensor) -> Registration:
        """Register ``frame`` to ``keyframe``; ``T_guess`` (4, 4) float64 is the last frame's ``T_kf``."""
        raise NotImplementedError

    def to_stamp(self, frame: PreparedFrame, twist: Tensor) -> None:
        """Move what :meth:`register` reads of ``frame`` (its points) to its stamp with ``twist``
        (6,) (``readout_time``): the dense pyramid's points, or the sparse front-end's ORB points."""
        raise NotImplementedError

    @staticmethod
    def memory(cfg: GCSlamConfig, camera: PinholeCamera, batch: int) -> dict[str, tuple[int, str]]:
        """Working memory beyond the images, for ``systems.memory``: ``{what: (bytes, why)}``."""
        return {}


class SparseFrontend(TrackingFrontend):
    """ORB features of every frame registered to the keyframe's (FastGO paper §IV-A1).

    With ``sparse.guided_radius > 0`` the matches are guided by the tracker's predicted pose
    (``T_guess``: the constant-velocity prediction of ``GCSlamConfig.motion_prior``, or the last
    frame's pose where there is none). A weak guided registration (few inliers, or few of the
    keypoints: ``sparse.guided_min_fraction``) is checked by brute-force matching inside
    :func:`~torchslam.registration.sparse.register_sparse_batch`. ``counts`` holds how many
    registrations kept their guided matches and how many took the brute-force result.
    """

    kind = Frontend.SPARSE

    def __init__(self, cfg: GCSlamConfig, camera: PinholeCamera, rays: Tensor | None, generator: torch.Generator,
                 readout: float = 0.0) -> None:
        super().__init__(cfg, camera, rays, generator, readout)
        self.counts = {"guided": 0, "fallback": 0, "depth_refined": 0}
        self._pixel_rays: Tensor | None = None

    def prepare(self, rgb: Tensor, depth: Tensor, keyframe: bool, lap: Callable[[str], None]) -> PreparedFrame:
        frame = PreparedFrame(rgb, depth)
        self.features(frame)
        lap("orb_extraction")
        return frame

    def register(self, keyframe: RegistrationTarget, frame: PreparedFrame, T_guess: Tensor) -> Registration:
        cfg = self.cfg.sparse
        if cfg.guided_radius <= 0:
            res = register_sparse(keyframe.features, frame.features, cfg, self.generator)
            return Registration(bool(res.success[0]), res.T_ij[0], res, int(res.num_inliers[0]))
        res = register_sparse_batch([keyframe.features], [frame.features], cfg, self.generator,
                                    T_pred=T_guess.to(torch.float64)[None], focal=self.camera.fx)
        self.counts["guided" if bool(res.guided[0]) else "fallback"] += 1
        return Registration(bool(res.success[0]), self._with_depth(keyframe, frame, res), res, int(res.num_inliers[0]))

    def to_stamp(self, frame: PreparedFrame, twist: Tensor) -> None:
        """The ORB points moved (:func:`~torchslam.registration.rolling.features_at_stamp`; the
        features as read kept in ``features_as_read``); the depth samples of
        :meth:`_with_depth` are moved as they are drawn."""
        feats = self.features(frame)
        frame.features_as_read = feats
        frame.features = features_at_stamp(feats, twist, self.camera.height, self.readout)
        frame.moved = twist

    @property
    def uses_keyframe_depth(self) -> bool:
        return self.cfg.depth_refine_points > 0

    def _with_depth(self, keyframe: RegistrationTarget, frame: PreparedFrame, res: SparseResult) -> Tensor:
        """The registration's pose, refined against the keyframe's depth (``depth_refine_points``)."""
        T = res.T_ij[0]
        n = self.cfg.depth_refine_points
        if n <= 0 or not bool(res.success[0]) or keyframe.depth is None:
            return T
        if self._pixel_rays is None:  # a distorted camera's are the front-end's; a pinhole camera's made once
            self._pixel_rays = self.rays if self.rays is not None else undistorted_rays(self.camera, device=frame.depth.device)
        pts = sample_depth_points(frame.depth, self._pixel_rays, n, self.cfg.sparse.min_depth, self.cfg.sparse.max_depth)
        if frame.moved is not None:  # the frame's rolling shutter: its depth samples to its stamp, as its ORB points
            cam = self.camera
            rows = cam.fy * pts[:, 1] / pts[:, 2] + cam.cy
            pts = correct_rows(pts[None], rows[None], torch.ones_like(rows, dtype=torch.bool)[None],
                               frame.moved.to(pts)[None], cam.height, self.readout)[0]
        T2, used = refine_with_depth(T, keyframe.depth, self.camera, pts, res.points_i[0], res.points_j[0], res.inliers[0],
                                     self.cfg.depth_refine_iterations, self.cfg.dense.depth_edge_tolerance,
                                     self.cfg.dense.correspondence_threshold, self.cfg.dense.sigma_floor_geometric,
                                     twist_i=getattr(keyframe, "twist", None), readout=self.readout)
        self.counts["depth_refined"] += used > 0
        return T2


class DenseFrontend(TrackingFrontend):
    """Dense photometric + geometric alignment to the current keyframe (FastGO paper §IV-A2)."""

    kind = Frontend.DENSE

    def prepare(self, rgb: Tensor, depth: Tensor, keyframe: bool, lap: Callable[[str], None]) -> PreparedFrame:
        frame = PreparedFrame(rgb, depth)
        if keyframe:
            self.features(frame)
            lap("orb_extraction")
        frame.dense = prepare_dense_frame(rgb[None], depth[None], self.camera, self.cfg.dense)
        lap("dense_preparation")
        return frame

    def to_stamp(self, frame: PreparedFrame, twist: Tensor) -> None:
        """The pyramid's points moved (:func:`~torchslam.registration.rolling.dense_frame_at_stamp`)."""
        frame.dense = dense_frame_at_stamp(frame.dense, twist.to(frame.dense.levels[0].points.dtype), self.readout)
        frame.moved = twist

    def register(self, keyframe: RegistrationTarget, frame: PreparedFrame, T_guess: Tensor) -> Registration:
        res = register_dense_frames(keyframe.dense, frame.dense, T_guess[None], self.cfg.dense)
        return Registration(bool(res.success[0]), res.T_ij[0], res, int(res.num_correspondences[0]))

    @staticmethod
    def memory(cfg: GCSlamConfig, camera: PinholeCamera, batch: int) -> dict[str, tuple[int, str]]:
        """The dense working pyramid."""
        working = dense_working_pixels(cfg, camera)
        return {"dense pyramid": (DENSE_BYTES_PER_WORKING_PIXEL * working * batch,
                                  f"image {camera.width}x{camera.height}, dense.width = {cfg.dense.width}")}


def dense_working_pixels(cfg: GCSlamConfig, camera: PinholeCamera) -> int:
    """Pixels of the dense working resolution (the image reduced by ``round(W / dense.width)``)."""
    factor = max(1, round(camera.width / cfg.dense.width))
    return (camera.width // factor) * (camera.height // factor)


_FRONTENDS: dict[Frontend, type[TrackingFrontend]] = {Frontend.SPARSE: SparseFrontend, Frontend.DENSE: DenseFrontend}


def frontend_class(kind: Frontend) -> type[TrackingFrontend]:
    """The front-end class of a :class:`Frontend` option."""
    return _FRONTENDS[kind]


def make_frontend(cfg: GCSlamConfig, camera: PinholeCamera, rays: Tensor | None, generator: torch.Generator,
                  readout: float = 0.0) -> TrackingFrontend:
    """The front-end ``cfg.frontend`` names, for one sequence (``readout``: its rolling shutter, seconds)."""
    return frontend_class(cfg.frontend)(cfg, camera, rays, generator, readout)
