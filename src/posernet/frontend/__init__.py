"""Image front end: the paper's stages (b)-(d) on real images, offline, on the CPU.

ROI proposals per image (:mod:`.proposals`), keypoint matching per image pair (:mod:`.features`),
the paper's box-matching rules (:mod:`.boxmatch`), OpenCV 5-point initial relative poses on
in-box keypoints (KP) and box centres (BB) (:mod:`.relpose`), two-view verification of every
pair's pose (inlier counts, pure rotation / plane, cheirality, static matches; :mod:`.verify`),
and view graphs of any set of
images (:mod:`.graphs`), tied together by :class:`ImageFrontend` (:mod:`.pipeline`) over the
images a user brings (:mod:`.images`). What its stages hand on is typed data (:mod:`.results`):
per-image :class:`ImageFeatures`, per-pair :class:`PairMatches` (matches and their verified
:class:`TwoViewGeometry`) in a :class:`MatchResult`, and the assembled
:class:`FrontendResult`. Each stage is swappable and has its own Hydra config group
(``proposals/``, ``matcher/``, ``box_matching/``, ``relpose/``). The synthetic generator
shares the box-matching rules, the 5-point step and the graph assembly.
"""

from .assembly import PairResult, assemble_view_graph, grow_connected
from .boxmatch import BoxMatchRules, match_boxes
from .cache import FrontendCache
from .features import Features, MatcherError, Matches, SiftMatcher, XFeatMatcher, make_matcher
from .images import (
    ImageError,
    ImageRecord,
    image_problem,
    parse_intrinsics,
    read_colmap_images,
    read_image,
    read_tum_trajectory,
    records_for_images,
)
from .pairs import PairOptions, PairSelection, global_descriptors, select_pairs
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
from .results import (
    FrontendResult,
    ImageFeatures,
    MatchResult,
    PairMatches,
    TwoViewGeometry,
    assemble_frontend_result,
)
from .verify import TwoView, VerifyRules, epipolar_consistent, keypoint_contrast, verify_two_view

__all__ = [
    "BoxMatchRules",
    "EdgeBoxes",
    "Features",
    "FileProposals",
    "FrontendCache",
    "FrontendResult",
    "FrontendSummary",
    "ImageError",
    "ImageFeatures",
    "ImageFrontend",
    "ImageRecord",
    "MatchResult",
    "MatcherError",
    "Matches",
    "PairMatches",
    "PairOptions",
    "PairResult",
    "PairSelection",
    "PoseOptions",
    "ProposalError",
    "Proposals",
    "SelectiveSearch",
    "SiftMatcher",
    "TwoView",
    "TwoViewGeometry",
    "VerifyRules",
    "XFeatMatcher",
    "assemble_frontend_result",
    "assemble_view_graph",
    "epipolar_consistent",
    "filter_proposals",
    "five_point",
    "global_descriptors",
    "grow_connected",
    "image_problem",
    "keypoint_contrast",
    "make_matcher",
    "match_boxes",
    "parse_intrinsics",
    "read_colmap_images",
    "read_image",
    "read_tum_trajectory",
    "records_for_images",
    "select_pairs",
    "verify_two_view",
]
