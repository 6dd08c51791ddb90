"""Interactions of the epipolar module: what the old epipolar-geometry Java applets had, in the viewer.

* **Click a pixel** of image 1 (or 2): its epipolar line in the other image, drawn on that image,
  and its ray in 3D from the camera's centre through the pixel, with the epipolar plane (both
  centres and the ray) cutting camera 2's image plane along that same line. The pixel comes from
  a click on the image shown as a plane in the camera's frustum in the 3D scene (viser scene
  images are clickable, GUI images are not), or from the number inputs (scripts, tests).
* **Drag a 3D point** (a transform gizmo, or the number inputs): its projections in both images,
  the epipolar plane through both camera centres and the point, and both epipolar lines move.
* **The four pose candidates** of E side by side (four small copies of the two-camera rig with
  the points triangulated by each, along the x axis), the one passing the cheirality test
  highlighted, with how many points each puts in front of both cameras.
* **Inliers and outliers** of RANSAC: the matches drawn across the image pair, inliers green,
  outliers red (the generic drawing shows keypoints and a sample of epipolar lines, not which
  matches RANSAC kept).

Which geometry is shown: the session's own F, E, candidates and pose once it has computed them,
else the dataset's ground truth (``session.truth``) when it has one; each folder says which.
World coordinates are camera 1's frame (the module's convention, and the generic drawing's):
camera 2 sees ``X_2 = R X_1 + t``.

The math is in typed functions (tested directly), the classes only wire it to viser: which geometry
and what a pixel or point determines in :mod:`.geometry`, the explorer in :mod:`.explorer`, the pose
candidates in :mod:`.candidates`, the inliers in :mod:`.matches`; this package's ``__init__`` lists
the interactions (``INTERACTIONS``) and re-exports their public names.
Reference: R. Hartley and A. Zisserman, Multiple View Geometry (2nd ed., 2004): section 6.2.2
(back-projection of a pixel to a ray), 9.1 (the epipolar plane and lines), 9.6.2-9.6.3 (the four
solutions of E and the cheirality test).
"""

from __future__ import annotations

from lab.viewer.interactions import Interaction
from lab.viewer.interactions.epipolar.candidates import (CANDIDATE_READS, CandidateAnalysis, PoseCandidates,
                                                         analyse_candidates, candidate_layout,
                                                         candidate_points)
from lab.viewer.interactions.epipolar.explorer import EpipolarExplorer
from lab.viewer.interactions.epipolar.geometry import (GEOMETRY_READS, PixelPick, PointMove, TwoViewGeometry,
                                                       check_pixel, explorer_overlays, move, observed_pairs,
                                                       pick, scene_depths, two_view_geometry)
from lab.viewer.interactions.epipolar.matches import MATCH_READS, MatchColours

INTERACTIONS: list[type[Interaction]] = [EpipolarExplorer, PoseCandidates, MatchColours]

__all__ = ["CANDIDATE_READS", "GEOMETRY_READS", "INTERACTIONS", "MATCH_READS", "CandidateAnalysis",
           "EpipolarExplorer", "MatchColours", "PixelPick", "PointMove", "PoseCandidates", "TwoViewGeometry",
           "analyse_candidates", "candidate_layout", "candidate_points", "check_pixel", "explorer_overlays",
           "move", "observed_pairs", "pick", "scene_depths", "two_view_geometry"]
