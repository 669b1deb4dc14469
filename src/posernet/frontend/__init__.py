"""Image front end: the paper's stages (b)-(d) on real images, offline, on the CPU.

ROI proposals per image (:mod:`.proposals`), keypoint matching per image pair (:mod:`.features`),
the paper's box-matching rules (:mod:`.boxmatch`), OpenCV 5-point initial relative poses on
in-box keypoints (KP) and box centres (BB) (:mod:`.relpose`), two-view verification of every
pair's pose (inlier counts, pure rotation / plane, cheirality, static matches; :mod:`.verify`),
and view graphs of any set of
images (:mod:`.graphs`), tied together by :class:`ImageFrontend` (:mod:`.pipeline`) over the
images a user brings (:mod:`.images`). Each stage is swappable and has its own Hydra config
group (``proposals/``, ``matcher/``, ``box_matching/``, ``relpose/``). The synthetic generator
shares the box-matching rules, the 5-point step and the graph assembly.
"""

from .boxmatch import BoxMatchRules, match_boxes
from .features import Features, MatcherError, Matches, SiftMatcher, XFeatMatcher, make_matcher
from .graphs import PairResult, assemble_view_graph, grow_connected
from .images import ImageError, ImageRecord, parse_intrinsics, read_image, records_for_images
from .pipeline import FrontendSummary, ImageFrontend
from .proposals import (
    EdgeBoxes,
    FileProposals,
    ProposalError,
    Proposals,
    SelectiveSearch,
    filter_proposals,
)
from .relpose import PoseOptions, five_point
from .verify import TwoView, VerifyRules, epipolar_consistent, keypoint_contrast, verify_two_view

__all__ = [
    "BoxMatchRules",
    "EdgeBoxes",
    "Features",
    "FileProposals",
    "FrontendSummary",
    "ImageError",
    "ImageFrontend",
    "ImageRecord",
    "MatcherError",
    "Matches",
    "PairResult",
    "PoseOptions",
    "ProposalError",
    "Proposals",
    "SelectiveSearch",
    "SiftMatcher",
    "TwoView",
    "VerifyRules",
    "XFeatMatcher",
    "assemble_view_graph",
    "epipolar_consistent",
    "filter_proposals",
    "five_point",
    "grow_connected",
    "keypoint_contrast",
    "make_matcher",
    "match_boxes",
    "parse_intrinsics",
    "read_image",
    "records_for_images",
    "verify_two_view",
]
