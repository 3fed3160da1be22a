"""Frame-to-frame RGB-D registration for GC-SLAM (paper §IV-A).

``sparse``: ORB matches, isometry outlier filter, batched RANSAC and robust refinement.
``dense``: DVO-style photometric + geometric alignment on an image pyramid.

Both return the relative pose ``T_ij`` (``p_i = T_ij p_j``: points of frame ``j`` expressed in
frame ``i``) and the inlier correspondences summarised as :class:`~torchslam.fastgo.PairStats`,
ready for FastGO.
"""
