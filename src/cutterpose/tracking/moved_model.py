"""The moved model: the edges the tracker fits on a broken edge (docs/tracking.md, "Broken
edges").

The edges tracking finds are the innermost rise of the broken pocket edge, off the design
edge that ``dm+b`` measures. The tracker fits the design contour moved edge by edge in the
face plane instead: design edge ``k`` shifted by ``d_k`` mm along its outward normal
(:func:`offset_polygon_mm`), the offsets measured at anchors (:func:`line_offsets_mm`) and
carried between them, the edge model (:mod:`cutterpose.image.edge_model`) predicting their
change with the view (:class:`MovedModel`); a tracked pose is then the design edge's.

Convention: edge ``k`` of the model runs from corner ``k`` to corner ``k + 1``
(``holder.json`` order) and corner ``i`` is the intersection of edges ``i - 1`` and ``i``.
"""

from __future__ import annotations

import numpy as np

from ..geometry.holder import Holder, outward_edge_normals
from ..geometry.pose import Pose
from ..image import edge_model as em

__all__ = ["offset_polygon_mm", "offset_edge_ends_mm", "offset_slope", "line_offsets_mm",
           "MovedModel", "VIEW_STEP", "VIEW_REACH"]

#: the view model's step along the line of sight for its slope, and how far from the anchor's
#: distance (relative) it is followed linearly (beyond, the offsets stay as there)
VIEW_STEP = 0.05
VIEW_REACH = 0.15


# ------------------------------------------------------------------------------------------
# the tracked edges of a broken edge: the design contour moved edge by edge in the face plane
def offset_polygon_mm(corners_mm: np.ndarray, offset_mm: np.ndarray) -> np.ndarray:
    """(N, 3) corners (holder frame, ``Z = 0``) of the polygon whose edge ``k`` is the design
    edge ``k`` moved by ``offset_mm[k]`` along its outward normal in the face plane (negative:
    into the pocket); corner ``i`` is where the moved edges ``i - 1`` and ``i`` meet (corners of
    nearly parallel neighbours are moved along the edge normal instead).

    ``offset_mm`` (N,): one offset per edge; (N, 2): an offset at each end of every edge
    (``[k, 0]`` at corner ``k``, ``[k, 1]`` at corner ``k + 1``): the moved edge is the line
    through both moved ends, tilted against the design edge when they differ."""
    c = np.asarray(corners_mm, float)
    d = np.asarray(offset_mm, float)
    n = outward_edge_normals(c)
    if d.ndim == 2:
        a = c + d[:, 0:1] * n                               # edge k: through a_k and b_k
        b = np.roll(c, -1, axis=0) + d[:, 1:2] * n
        t = b - a
        n_m = np.column_stack([t[:, 1], -t[:, 0]]) / np.linalg.norm(t, axis=1)[:, None]
        n_m *= np.sign(np.einsum("ij,ij->i", n_m, n))[:, None]
        rhs = np.einsum("ij,ij->i", n_m, a)
        q = a.copy()
    else:
        n_m = n
        rhs = np.einsum("ij,ij->i", n, c) + d            # edge k: n_k . x = n_k . c_k + d_k
        q = c + d[:, None] * n
    # corner i: edges i - 1 (p . x = e) and i (n_m . x = rhs), Cramer's rule (a 2 x 2 system
    # per corner; np.linalg.solve's overhead was most of a tracked frame's 0.2 ms here)
    pn, e = np.roll(n_m, 1, axis=0), np.roll(rhs, 1)
    det = pn[:, 0] * n_m[:, 1] - pn[:, 1] * n_m[:, 0]
    ok = np.abs(det) > 1e-6
    q[ok, 0] = ((e * n_m[:, 1] - rhs * pn[:, 1]) / np.where(ok, det, 1.0))[ok]
    q[ok, 1] = ((pn[:, 0] * rhs - n_m[:, 0] * e) / np.where(ok, det, 1.0))[ok]
    return np.column_stack([q, np.zeros(len(q))])


def offset_edge_ends_mm(corners_mm: np.ndarray, offset_mm: np.ndarray) -> np.ndarray:
    """(2N, 3) ends of the moved edges (holder frame, ``Z = 0``): rows ``k`` the start of edge
    ``k`` (design corner ``k`` moved by ``offset_mm[k, 0]`` along the edge's outward normal),
    rows ``N + k`` its end (corner ``k + 1`` by ``offset_mm[k, 1]``); ``offset_mm`` (N,) is
    the same offset at both ends."""
    c = np.asarray(corners_mm, float)
    d = np.asarray(offset_mm, float)
    d = np.column_stack([d, d]) if d.ndim == 1 else d
    n = outward_edge_normals(c)
    e = np.concatenate([c + d[:, 0:1] * n, np.roll(c, -1, axis=0) + d[:, 1:2] * n])
    return np.column_stack([e, np.zeros(len(e))])


def offset_slope(pose: Pose, points_mm: np.ndarray, normals: np.ndarray, L: np.ndarray,
                  K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances (ideal px) of the projected face-plane ``points_mm`` (M, 2) to the
    lines ``L`` (M, 3), and their derivatives w.r.t. an outward shift of each point along its
    ``normals`` (M, 2) in the face plane (px per mm)."""
    X = np.column_stack([points_mm, np.zeros(len(points_mm))]) @ pose.R.T + pose.t_mm
    Rn = np.column_stack([normals, np.zeros(len(normals))]) @ pose.R.T   # d X_cam / d shift
    uv = X[:, :2] / X[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    duv = (Rn[:, :2] - X[:, :2] / X[:, 2:3] * Rn[:, 2:3]) / X[:, 2:3] @ K[:2, :2].T
    return (L[:, 0] * uv[:, 0] + L[:, 1] * uv[:, 1] + L[:, 2],
            L[:, 0] * duv[:, 0] + L[:, 1] * duv[:, 1])


def line_offsets_mm(pose: Pose, lines: np.ndarray, seen: np.ndarray, holder: Holder, K,
                    per_end: bool = True) -> np.ndarray:
    """(N, 2) outward offsets (mm, face plane) of the image ``lines`` (N, 3; ideal px) from
    the design edges seen with ``pose``: the shift of each end of design edge ``k`` along its
    outward normal that puts it, projected, on line ``k`` (Newton); ``per_end=False``: one
    shift for both ends of an edge (least squares). NaN for edges not ``seen``."""
    c = np.asarray(holder.corners_mm, float)
    nrm = holder.edge_normals
    K = np.asarray(K, float)
    out = np.full((len(c), 2), np.nan)
    ks = np.nonzero(seen)[0]
    if len(ks) == 0:
        return out
    ends = np.concatenate([c[ks], np.roll(c, -1, axis=0)[ks]])     # (2m, 2)
    nn = np.concatenate([nrm[ks], nrm[ks]])
    L = np.concatenate([lines[ks], lines[ks]])
    m = len(ks)
    d = np.zeros(2 * m)
    for _ in range(3):   # the projection is nearly linear over a millimetre
        r, g = offset_slope(pose, ends + d[:, None] * nn, nn, L, K)
        if per_end:
            d = d - r / g
        else:
            step = (r[:m] * g[:m] + r[m:] * g[m:]) / (g[:m] ** 2 + g[m:] ** 2)
            d = d - np.concatenate([step, step])
    out[ks] = np.column_stack([d[:m], d[m:]])
    return out



class MovedModel:
    """The tracker's moved model (a part of :class:`~cutterpose.tracking.Tracker`): the
    offsets of the tracked edges from the design edges, their view-dependent part, and the
    model corners and edge ends fitted to the tracked lines.

    State (set by :meth:`_reset_model`): ``_offset_mm`` (N, 2) the carried offsets (None:
    the design contour), ``_measured`` the edges an anchor has measured, ``_offset_spread_mm``
    their spread, ``_model_mm`` / ``_ends_mm`` the model's corners and edge ends, and the view
    model (``_view_radius_mm``, ``_view_look``, ``_delta_mm``, ``_view_ref``). Reads
    ``holder``, ``K`` and ``tp`` of the tracker."""

    def _reset_model(self) -> None:
        """The design contour, no offsets, no view model."""
        # the model the tracked edges are fitted with: the design corners, or (dm+b, dm+r)
        # the design contour moved by the offsets of the edges tracked from the design edge
        self._offset_mm: np.ndarray | None = None
        self._measured: np.ndarray | None = None   # (N,) edges an anchor has measured
        self._offset_spread_mm = 0.0   # the measured edges' offsets' spread about the median
        self._model_mm = self.holder.points_holder_mm
        # the ends of every model edge (2N, 3): P_k, then P_k+1, fitted to the tracked lines
        self._ends_mm = np.concatenate([self._model_mm, np.roll(self._model_mm, -1, axis=0)])
        # the offsets' view-dependent part (dm+b, ``view_model``): the edge model's offset of
        # the innermost rise at each edge end (N, 2) in the current view, for the band fit's
        # radius at each end and its edge shape (None: no model, offsets are lengths)
        self._view_radius_mm: np.ndarray | None = None
        self._view_look = None
        self._delta_mm = np.zeros((len(self.holder.corners_mm), 2))
        #: the view model linearised at the last anchor along the line of sight: (distance
        #: |t| there, the offsets there, their change per relative change of distance)
        self._view_ref: tuple | None = None

    def _set_view_model(self, band) -> None:
        """The edge model the offsets follow the view with (``view_model``), from a band fit
        (:class:`~cutterpose.solvers.edge_band.BandPose`; None keeps the last): the fit's
        median radius over its segments at every edge end and its edge shape, with the nominal
        photometry (the shipped offset grid's). One radius, not each edge's: an edge's own
        radius rests on its four segments, and a wrong one (3.98 mm among 0.2-0.4 on the
        analytic ``field`` approach) put that edge's model 0.86 mm inside and the tracker
        lost it; the common trend, a depth error, is the part that matters (docs/RESULTS.md
        section 14)."""
        if not self.tp.view_model or band is None:
            return
        r = band.fit.radius_median_mm
        if not np.isfinite(r):
            return
        self._view_radius_mm = np.full((len(self.holder.corners_mm), 2), float(r))
        self._view_look = em.EdgeLook(shape=band.fit.best.look.shape)

    def _view_delta(self, pose: Pose) -> np.ndarray | None:
        """The edge model's outward offsets (N, 2; mm in the face plane) of the innermost rise
        at every edge end seen with ``pose``; zeros without a model, None where the view lies
        outside the shipped offset grid (the caller keeps the last)."""
        if self._view_radius_mm is None:
            return np.zeros_like(self._delta_mm)
        view = em.edge_views(pose.R, pose.t_mm, self.K, self.holder, self._view_look)
        w = em.tabulated_w_px(self._view_radius_mm[..., None], view, self._view_look)
        if w is None or not np.all(np.isfinite(w)):
            return None
        return w[..., 0] / view.a_s

    def _follow_view(self, pose: Pose) -> None:
        """The moved model at ``pose``'s distance: the view model linearised at the last
        anchor (``_view_ref``), followed up to ``VIEW_REACH`` of its distance."""
        if self._view_ref is None or self._offset_mm is None:
            return
        s_a, d_a, g = self._view_ref
        u = float(np.clip(np.linalg.norm(pose.t_mm) / s_a - 1.0, -VIEW_REACH, VIEW_REACH))
        self._set_model(d_a + g * u)

    def _set_model(self, delta_mm: np.ndarray) -> None:
        """The moved model (``_model_mm``, ``_ends_mm``) from the carried offsets and the
        view's part ``delta_mm``."""
        self._delta_mm = delta_mm
        if self._offset_mm is None:
            return
        c = np.asarray(self.holder.corners_mm, float)
        # corner i's ends: (i, 0) of edge i - 1, (i, 1) of edge i -> per edge (start, end)
        dv = np.column_stack([self._delta_mm[:, 1], np.roll(self._delta_mm[:, 0], -1)])
        off = self._offset_mm + dv
        self._model_mm = offset_polygon_mm(c, off)
        # one offset per edge: the moved polygon's corners are its edges' ends (as before the
        # ends had offsets of their own)
        self._ends_mm = offset_edge_ends_mm(c, off) if self.tp.anchor_ends else \
            np.concatenate([self._model_mm, np.roll(self._model_mm, -1, axis=0)])

    def _set_offsets(self, pose: Pose, lines: np.ndarray, seen: np.ndarray, std_dof,
                     k: int, gain: float, band=None) -> None:
        """Each seen edge's offsets (mm, face plane, outward normal) from the design edge: the
        shift of each end of design edge ``k`` that puts it, projected at the design ``pose``,
        on the tracked line (Newton; ``anchor_ends=False``: one shift for both ends, least
        squares), weighted by ``gain`` against the offsets carried; an edge not seen keeps its
        last offsets (the seen edges' median the first time)."""
        c = np.asarray(self.holder.corners_mm, float)
        ks = np.nonzero(seen)[0]
        if len(ks) == 0:
            return
        d = line_offsets_mm(pose, lines, seen, self.holder, self.K, self.tp.anchor_ends)[ks]
        # what is carried is the part the view does not explain (the measured offsets minus
        # the edge model's at this pose); without a model, the offsets themselves
        self._set_view_model(band)
        delta = self._view_delta(pose)
        delta = self._delta_mm if delta is None else delta
        self._view_ref = None
        if self._view_radius_mm is not None:
            # the model's slope along the approach: the camera 5 % closer on its line of sight
            # (between anchors the view changes mostly by the distance; evaluating the model
            # at each frame's own pose would add the pose's noise in rotation to the offsets)
            near = self._view_delta(Pose(pose.R, pose.t_mm * (1.0 - VIEW_STEP)))
            if near is not None:
                self._view_ref = (float(np.linalg.norm(pose.t_mm)), delta,
                                  (delta - near) / VIEW_STEP)
        d = d - np.column_stack([delta[:, 1], np.roll(delta[:, 0], -1)])[ks]
        if self._offset_mm is None:
            off, gain = np.full((len(c), 2), float(np.median(d))), 1.0
        else:
            off = self._offset_mm.copy()
        off[ks] += gain * (d - off[ks])
        self._offset_mm = off
        if self._measured is None:
            self._measured = np.zeros(len(c), bool)
        self._measured[ks] = True
        v = off[self._measured].mean(axis=1)
        self._offset_spread_mm = float(1.4826 * np.median(np.abs(v - np.median(v))))
        self._set_model(delta)
        self._anchor_t_mm, self._anchor_frame = pose.t_mm.copy(), k
        self._anchor_std = np.where(np.isfinite(std_dof), std_dof, 0.0)
        self._anchors += 1
