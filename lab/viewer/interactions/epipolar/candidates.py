"""The four pose candidates of E side by side, the one that passes the cheirality test highlighted.

Four small copies of the two-camera rig, one per ``[R | t]`` of the essential matrix, laid out two by two
below the scene (as H&Z's figure 9.12), each with the points it triangulates (blue in front of both cameras,
red behind one), and a table of how many points each puts in front of both cameras: the one with
the most is what ``recover_pose`` keeps. Reference: Hartley & Zisserman (2nd ed.), sections
9.6.2-9.6.3 (the four solutions of E and the cheirality test).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core.errors import InvalidValue, LabError, MissingInput
from lab.geometry.camera import pixels_to_normalized
from lab.geometry.camera_views import camera_centre
from lab.geometry.triangulation import point_depths, projection_matrix, triangulate_dlt
from lab.modules.epipolar import cheirality_counts, essential_candidates
from lab.viewer.drawing import frustum_segments
from lab.viewer.interactions import Interaction, InteractionContext, LegendEntry, NamedHandles, Swatch
from lab.viewer.interactions.epipolar.geometry import (GEOMETRY_READS, matrix_or_none, observed_pairs,
                                                       scene_depths, two_view_geometry)

#: Colours (RGB, 0-255): the rig that passes, the others, points in front of both cameras, behind one.
CHOSEN_COLOR = (30, 190, 60)
OTHER_COLOR = (150, 150, 150)
IN_FRONT_COLOR = (40, 120, 255)
BEHIND_COLOR = (230, 40, 40)
#: Most points per candidate drawn in 3D.
MAX_CANDIDATE_POINTS = 300
#: The state values :class:`PoseCandidates` reads (through ``ctx.values``; each one of the pipeline's views).
CANDIDATE_READS = (*GEOMETRY_READS, "candidates", "E")


def candidate_layout(count: int, spacing: float, *, columns: int = 2, first: float = 1.0) -> np.ndarray:
    """Offsets ``(count, 3)`` of the copies of a rig drawn in a grid ``columns`` wide, ``spacing`` apart:
    columns along x centred on the rig, rows below it (+y is down), the first ``first`` spacings down.

    Two columns keep the four candidates of E about as wide as the scene they sit under, so the tab's
    first camera shows the scene, its cameras and the candidates at a size one can read (a row of four
    was four times wider than the scene).
    """
    if count < 0 or columns < 1 or not np.isfinite(spacing) or spacing <= 0:
        raise InvalidValue("spacing", f"expected a positive spacing, a count >= 0 and columns >= 1, got "
                                      f"{spacing}, {count} and {columns}")
    index = np.arange(count)
    offsets = np.zeros((count, 3))
    offsets[:, 0] = (index % columns - (min(columns, max(count, 1)) - 1) / 2.0) * spacing
    offsets[:, 1] = (first + index // columns) * spacing
    return offsets


def candidate_points(candidates: np.ndarray, K1: np.ndarray, K2: np.ndarray, x1: np.ndarray,
                     x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs triangulated by each candidate pose and whether each lies in front of both cameras.

    For each ``[R | t]`` of ``candidates`` ``(C, 3, 4)``: DLT triangulation of ``x1``, ``x2`` ``(N, 2)``
    with ``P1 = K1 [I | 0]``, ``P2 = K2 [R | t]`` (``cv2.triangulatePoints``). Returns the points
    ``(C, N, 3)`` (camera 1 frame) and ``(C, N)`` bool: finite with positive depth in both cameras
    (the cheirality test of H&Z section 9.6.3; what ``cheirality_counts`` counts, in pixels here).
    """
    candidates = np.asarray(candidates, dtype=np.float64)
    x = np.stack([np.asarray(x1, dtype=np.float64), np.asarray(x2, dtype=np.float64)])
    P1 = projection_matrix(K1, np.eye(3), np.zeros(3))
    points, in_front = [], []
    for candidate in candidates:
        P = np.stack([P1, projection_matrix(K2, candidate[:, :3], candidate[:, 3])])
        X = triangulate_dlt(P, x)
        finite = np.all(np.isfinite(X), axis=1)
        depth = point_depths(P, np.where(finite[:, None], X, 0.0))
        points.append(X)
        in_front.append(finite & (depth[0] > 0) & (depth[1] > 0))
    return np.array(points).reshape(len(candidates), -1, 3), np.array(in_front).reshape(len(candidates), -1)


# ----------------------------------------------------------------------------------------------------
# Interaction 2: the four pose candidates side by side
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CandidateAnalysis:
    """The four candidates of E and their cheirality test.

    ``candidates`` ``(4, 3, 4)``; ``counts`` ``(4,)`` points in front of both cameras (of ``total``);
    ``chosen`` the candidate with the most (what ``recover_pose`` keeps); ``points`` ``(4, N, 3)`` and
    ``in_front`` ``(4, N)`` the triangulated pairs drawn (candidate units: ``|t| = 1``); ``far`` the
    95th-percentile depth of the chosen candidate's points; each copy is drawn ``scale`` times its size,
    shifted by ``offsets`` ``(4, 3)``; ``source`` says where E / the candidates come from.
    """

    candidates: np.ndarray
    counts: np.ndarray
    chosen: int
    total: int
    points: np.ndarray
    in_front: np.ndarray
    far: float
    scale: float
    offsets: np.ndarray
    source: str


CANDIDATE_NAMES = ("(R1, t)", "(R2, t)", "(R1, -t)", "(R2, -t)")


def analyse_candidates(candidates: np.ndarray, K1: np.ndarray, K2: np.ndarray, x1: np.ndarray,
                       x2: np.ndarray, *,
                       size: float | None = None, source: str = "") -> CandidateAnalysis:
    """Test and triangulate each candidate pose, and lay small copies of the rig out side by side.

    ``counts`` are :func:`lab.modules.epipolar.cheirality_counts` of the normalized pairs ``K^-1 x``
    (exactly what ``recover_pose`` compares), ``chosen`` their argmax. At most
    :data:`MAX_CANDIDATE_POINTS` pairs are triangulated for drawing (:func:`candidate_points`). Each
    copy is scaled so that the chosen candidate's far depth is ``size`` in the scene (default: its own
    size), and the copies go two by two every ``1.6 size``, the first row ``0.9`` spacings below the rig
    (:func:`candidate_layout`): under the scene and apart from each other.
    """
    candidates = np.asarray(candidates, dtype=np.float64)
    if candidates.ndim != 3 or candidates.shape[1:] != (3, 4):
        raise InvalidValue("candidates", f"expected (C, 3, 4) stacked [R | t], got {candidates.shape}")
    x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, dtype=np.float64).reshape(-1, 2)
    if len(x1) == 0 or len(x1) != len(x2):
        raise MissingInput("x1", f"no matched pairs to test the candidates with ({len(x1)} and {len(x2)} "
                                 "points)")
    counts = cheirality_counts(candidates, pixels_to_normalized(x1, K1), pixels_to_normalized(x2, K2))
    chosen = int(np.argmax(counts))
    step = max(1, len(x1) // MAX_CANDIDATE_POINTS)
    points, in_front = candidate_points(candidates, K1, K2, x1[::step], x2[::step])
    depth = points[chosen][in_front[chosen], 2]
    baseline = float(np.linalg.norm(candidates[chosen][:, 3])) or 1.0
    far = float(np.percentile(depth, 95)) if len(depth) >= 3 else 8.0 * baseline
    size = far if size is None else float(size)
    offsets = candidate_layout(len(candidates), 1.6 * size, first=0.9)
    return CandidateAnalysis(candidates, counts, chosen, len(x1), points, in_front, far, size / far, offsets,
                             source)


class PoseCandidates(Interaction):
    """The four ``[R | t]`` of E drawn side by side, each with the points it triangulates; the one with the
    points in front of both cameras (cheirality) highlighted."""

    title = "The four pose candidates of E"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.nodes = NamedHandles()
        self.analysis: CandidateAnalysis | None = None
        self._key: tuple | None = None
        self._state: Mapping[str, Any] = {}
        self.show_box = self.track(ctx.gui.add_checkbox("show in 3D", True,
                                                        hint="draw the four rigs in the scene"))
        self.table_md = self.track(ctx.gui.add_markdown(""))
        self.show_box.on_update(lambda _: ctx.guarded(self._redraw)())

    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(CANDIDATE_READS, state)
        key = tuple(id(state.get(n)) for n in ("candidates", "E", "K1", "K2", "x1", "inliers", "pose", "R"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self._state = state
            try:
                self.analysis = self._analyse(state, self.ctx.session.truth)
            except LabError as exc:
                self.analysis = None
                self.table_md.content = f"{exc.reason}"
            self._redraw()

    def _analyse(self, state: Mapping[str, Any], truth: Mapping[str, Any]) -> CandidateAnalysis | None:
        geometry = two_view_geometry(state, truth)
        if state.get("candidates") is not None:
            candidates, source = np.asarray(state["candidates"]), "the session (decompose_essential)"
        elif matrix_or_none(truth.get("E")) is not None:
            candidates, source = essential_candidates(truth["E"]), "the ground truth E"
        else:
            raise MissingInput("candidates", "No candidates yet: run decompose_essential (this dataset has "
                                             "no ground truth E to show instead).")
        if geometry is None or geometry.K1 is None or geometry.K2 is None:
            raise MissingInput("K1", "No K: the candidates cannot be tested.")
        pairs = observed_pairs(state, truth)
        if pairs is None:
            raise MissingInput("x1", "No matches to triangulate yet: run match_features.")
        _, far = scene_depths(geometry, pairs)  # in the units of the scene drawn (the explorer's)
        return analyse_candidates(candidates, geometry.K1, geometry.K2, *pairs, size=0.35 * far,
                                  source=source)

    def _redraw(self) -> None:
        with self.lock:
            self.nodes.clear()
            a = self.analysis
            if a is None:
                return
            self.table_md.content = self._table(a)
            if self.show_box.value:
                self._draw(a)

    def _table(self, a: CandidateAnalysis) -> str:
        rows = ["| # | candidate | in front of both | |", "|---|---|---|---|"]
        for i, count in enumerate(a.counts):
            mark = "**✓ passes (chosen)**" if i == a.chosen else ""
            rows.append(f"| {i + 1} | {CANDIDATE_NAMES[i] if i < 4 else i} | {int(count)} / {a.total} | "
                        f"{mark} |")
        pose = self._state.get("pose")
        note = ""
        if pose is not None:
            same = np.allclose(np.asarray(pose), a.candidates[a.chosen], atol=1e-9)
            note = ("  \nThe chosen candidate is " + ("" if same else "**not** ")
                    + "the pose recover_pose returned.")
        return (f"Candidates from {a.source}; points: the session's inliers (or the truth's exact pairs). "
                "Drawn below the scene, two by two: green rig = passes, blue points in front of both "
                "cameras, red behind one.\n\n" + "\n".join(rows) + note)

    def _draw(self, a: CandidateAnalysis) -> None:
        for i in range(len(a.candidates)):
            self._draw_candidate(a, i)

    def _draw_candidate(self, a: CandidateAnalysis, i: int) -> None:
        """Candidate ``i``'s rig (green when it passes), its points (blue in front, red behind) and label."""
        scene, node = self.ctx.scene, self.ctx.node
        candidate, offset = a.candidates[i], a.offsets[i]
        spacing = 1.6 * a.far * a.scale
        size = 0.06 * spacing
        radius = 1.15 * a.far  # points farther than this from camera 1 are not drawn (candidate units)
        color = CHOSEN_COLOR if i == a.chosen else OTHER_COLOR
        centres = a.scale * np.stack([np.zeros(3), camera_centre(candidate[:, :3], candidate[:, 3])])
        axes = [np.eye(3), candidate[:, :3].T]  # camera to world
        outline = np.array([[-1, -0.75, 1.5], [1, -0.75, 1.5], [1, 0.75, 1.5], [-1, 0.75, 1.5]])
        segments = [frustum_segments(centre, centre + (outline * size) @ rotation.T)
                    for centre, rotation in zip(centres, axes, strict=True)]
        segments.append(np.array([[centres[0], centres[1]]], dtype=np.float32))
        rig = np.concatenate(segments) + offset.astype(np.float32)
        base = f"candidates/{i}"
        self.nodes.put(f"{base}/rig", lambda: scene.add_line_segments(
            node("candidates", str(i), "rig"), points=rig, colors=color,
            thickness=4.0 if i == a.chosen else 2.0, thickness_units="screen"))
        X, front = a.points[i], a.in_front[i]
        shown = np.all(np.isfinite(X), axis=1) & (np.linalg.norm(X, axis=1) <= radius)
        if shown.any():
            colors = np.where(front[shown, None], np.array(IN_FRONT_COLOR),
                              np.array(BEHIND_COLOR)).astype(np.uint8)
            points = (a.scale * X[shown] + offset).astype(np.float32)
            self.nodes.put(f"{base}/points", lambda: scene.add_point_cloud(
                node("candidates", str(i), "points"), points=points, colors=colors, point_size=0.01 * spacing,
                point_shape="circle"))
        text = (f"#{i + 1} {CANDIDATE_NAMES[i] if i < 4 else ''}: {int(a.counts[i])}/{a.total} in front"
                + (" ✓ passes" if i == a.chosen else ""))
        above = tuple(offset + np.array([0.0, -0.3 * spacing, 0.0]))  # up is -y
        self.nodes.put(f"{base}/label", lambda: scene.add_label(node("candidates", str(i), "label"), text,
                                                                position=above, anchor="bottom-center"))

    def scene_nodes(self) -> list[str]:
        with self.lock:
            return self.nodes.names()

    def legend(self) -> list[LegendEntry]:
        with self.lock:
            a = self.analysis
            if a is None or not self.show_box.value:
                return []
            return [LegendEntry("pose candidates", "rigs", len(a.candidates),
                                (Swatch(CHOSEN_COLOR, "the candidate that passes (recover_pose's)"),
                                 Swatch(OTHER_COLOR, "the other three"),
                                 Swatch(IN_FRONT_COLOR, "points in front of both cameras"),
                                 Swatch(BEHIND_COLOR, "points behind one")),
                                "below the scene, two by two, each labelled with its count")]

    def close(self) -> None:
        with self.lock:
            self.nodes.clear()
        super().close()


__all__ = ["CANDIDATE_NAMES", "CANDIDATE_READS", "CandidateAnalysis", "PoseCandidates", "analyse_candidates",
           "candidate_layout", "candidate_points"]
