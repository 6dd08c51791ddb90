"""RANSAC's inliers and outliers: the matches drawn across the image pair, inliers green, outliers red.

The generic drawing shows keypoints and a sample of epipolar lines, not which matches RANSAC kept;
with a ground truth, the summary adds how many inliers are right matches (what the pipeline's
evaluation measured when RANSAC ran).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import Any

import numpy as np

from lab.core.values import ImageSet
from lab.viewer.drawing import match_pair_image
from lab.viewer.interactions import Interaction, InteractionContext

#: The state values :class:`MatchColours` reads (through ``ctx.values``; each one of the pipeline's views),
#: and the step whose evaluation judged the inliers against the truth.
MATCH_READS = ("images", "x1", "x2", "inliers", "F")
RANSAC_STEP = "estimate_fundamental_ransac"


# ----------------------------------------------------------------------------------------------------
# Interaction 3: inliers and outliers on the image pair
# ----------------------------------------------------------------------------------------------------
class MatchColours(Interaction):
    """The matches drawn across the image pair: RANSAC's inliers green, its outliers red."""

    title = "Matches: inliers and outliers"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self._key: tuple | None = None
        self.picture: np.ndarray | None = None
        self.counts: tuple[int, int] | None = None  # (inliers, outliers); None before RANSAC
        self.summary_md = self.track(ctx.gui.add_markdown(""))
        with ctx.images:
            self.panel = self.track(ctx.gui.add_image(np.zeros((8, 8, 3), np.uint8), label="matches",
                                                      format="jpeg",
                                                      order=1001.0, visible=False))

    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(MATCH_READS, state)
        key = tuple(id(state.get(n)) for n in ("images", "x1", "x2", "inliers"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            images, x1, x2 = state.get("images"), state.get("x1"), state.get("x2")
            if not isinstance(images, ImageSet) or len(images) != 2 or x1 is None or x2 is None \
                    or len(x1) != len(x2):
                self.picture, self.counts = None, None
                self.panel.visible = False
                self.summary_md.content = "No matches yet: run match_features."
                return
            inliers = state.get("inliers")
            if inliers is not None and np.shape(inliers) != (len(x1),):
                inliers = None
            self.picture = match_pair_image(images[0], images[1], x1, x2, inliers)
            self.panel.image = self.picture
            self.panel.visible = True
            if inliers is None:
                self.counts = None
                self.panel.label = f"{len(x1)} matches (yellow: RANSAC has not classified them yet)"
                self.summary_md.content = (f"{len(x1)} matches, drawn in yellow in the Images panel; run "
                                           "estimate_fundamental_ransac to see its inliers (green) and "
                                           "outliers (red).")
                return
            inliers = np.asarray(inliers, dtype=bool)
            self.counts = (int(inliers.sum()), int((~inliers).sum()))
            self.panel.label = f"matches: {self.counts[0]} inliers (green), {self.counts[1]} outliers (red)"
            text = (f"RANSAC kept {self.counts[0]} of {len(x1)} matches (green), rejected {self.counts[1]} "
                    "(red).")
            if self.ctx.session.truth and state.get("F") is not None:
                # what the pipeline's evaluation (evaluate_fundamental) measured when RANSAC ran
                scores = self.ctx.session.metrics.get(RANSAC_STEP, {})
                if "inlier_precision" in scores and "inlier_recall" in scores:
                    text += (f"  \nAgainst the ground truth: {scores['inlier_precision']:.1%} of the inliers "
                             f"are right matches, and {scores['inlier_recall']:.1%} of the right matches are "
                             "inliers.")
            self.summary_md.content = text


__all__ = ["MATCH_READS", "RANSAC_STEP", "MatchColours"]
