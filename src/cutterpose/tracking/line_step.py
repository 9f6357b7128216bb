"""The line step: a tracked frame's pose from the edges round the predicted model.

1. **edges**: the field chain's line step :func:`cutterpose.image.edges.robust_edge_lines` on
   the model edges projected with the predicted pose (grey-level profiles across each edge
   within +-``band_half_width_px``, the *innermost* rise of a broken edge, LMedS + Tukey IRLS
   lines, an edge *seen* when its inliers cover ``min_support`` of it and it lies within
   ``shift_fraction`` of the band of its prediction): an edge under a slurry lump, behind the
   cutter's silhouette or rounded beyond recognition is left out, not forced;
2. **pose**: Gauss-Newton on the distances of the projected ends of every *seen* edge to its
   line (ideal px), started at the prediction (Drummond & Cipolla 2002), no coarse search: a
   corner whose other edge is hidden still counts through its seen one. A seen edge far off
   the fitted model while the others fit (``line_outlier_*``) is left out and the pose fitted
   again. The bands are re-centred on the fitted pose and the edges found again while the fit
   moved them (by more than ``centred_fraction`` of the band, up to ``max_passes``). The std
   per DOF is the Gauss-Newton covariance ``s^2 (J^T J)^-1`` as in :mod:`cutterpose.pipeline`;
3. **checks**: at least half the holder's edges seen (``min_line_share``; two per direction),
   the bands settled, the RMS and largest model-to-edge distance below ``max_rms_px`` /
   ``max_corner_residual_px``, and the seen edges fixing every DOF within ``max_std_ratio`` of
   the std all edges would give. A frame that fails any of them falls back to the full
   measurement and says why.

Reference: T. Drummond, R. Cipolla, "Real-time visual tracking of complex structures", PAMI
24(7), 2002 (edge search along normals of the projected model).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..geometry.pose import Pose, pixel_jacobian
from ..image import FeatureParams
from ..image.edges import robust_edge_lines
from ..image.lines import intersect_consecutive
from ..pipeline import DOF_NAMES
from .moved_model import offset_slope
from .result import TrackResult

__all__ = ["LineStep", "bands_moved_px", "LINE_SCALE_PX"]

#: the scale (px) of a tracked edge's distance from the model, against which an unmeasured
#: edge's offset prior is weighed (the tracked frames' RMS is 0.3-0.6 px on broken edges)
LINE_SCALE_PX = 0.3


def bands_moved_px(r_start: np.ndarray, r: np.ndarray) -> float:
    """How far a pass's pose fit moved the bands' centres (px): the largest change of a seen
    edge end's distance to its line (``r_start`` at the pass's start pose, ``r`` at its
    fitted pose). The next pass centres its bands on the fitted pose, so this is how far they
    move; how far the edges lie from the model (``r`` itself) is the residual checks' to
    judge (a worn edge's break varies along it and leaves a px or two however the bands are
    centred)."""
    return float(np.max(np.abs(np.asarray(r_start) - np.asarray(r))))



class LineStep:
    """The line step of :class:`~cutterpose.tracking.Tracker` (module doc): reads the moved
    model (``_model_mm``, ``_ends_mm``, ``_measured``, ``_offset_spread_mm``), the camera,
    ``K``, ``tp``, the field chain's line parameters (``_refine_params``, ``_line_cache``)
    and the last full measurement's corner RMS (``_rms_ref``)."""

    def _project(self, pose: Pose) -> np.ndarray | None:
        """The model corners projected with ``pose`` (ideal px, holder order); None if the
        holder is behind the camera."""
        X = pose.apply(self._model_mm)
        if np.any(X[:, 2] <= 0):
            return None
        return X[:, :2] / X[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]

    def _line_params(self, half_width_px: float, shift_px: float) -> FeatureParams:
        """The field chain's line parameters for a band of +-``half_width_px`` about the
        predicted edges; a seen line lies within ``shift_px`` of its prediction (plus the
        field chain's outward allowance for a broken edge, capped by the band)."""
        key = (half_width_px, shift_px)
        p = self._line_cache.get(key)
        if p is None:
            out = min(self._refine_params.max_outward_shift_px,
                      max(half_width_px - shift_px - 1.0, 0.0))
            p = replace(self._refine_params, refine_half_width_px=half_width_px,
                        max_line_shift_px=shift_px, max_outward_shift_px=out,
                        min_line_support=self.tp.min_support,
                        corner_trim_px=max(self.tp.end_trim_px, half_width_px + 4.0))
            self._line_cache[key] = p
        return p

    def _lines_at(self, img: np.ndarray, pose: Pose, hw: float, lap=None):
        """The tracked edges' lines (ideal px) in bands of +-``hw`` px round the model
        projected with ``pose``: ``(lines, seen, support)``, or why there are none."""
        tp = self.tp
        corners_pred = self._project(pose)
        if corners_pred is None:
            return "the predicted holder is behind the camera"
        pred_px = self.camera.distort_px(corners_pred)
        if not np.all(self.camera.in_image(pred_px, 2 * hw)):
            return "the predicted holder leaves the image"
        # a crop round the predicted pocket (float32: sub-pixel grey-level profiles)
        m = hw + 4.0
        u0, v0 = np.maximum(np.floor(pred_px.min(axis=0) - m), 0).astype(int)
        u1, v1 = np.ceil(pred_px.max(axis=0) + m + 1).astype(int)
        sub = img[v0:v1, u0:u1].astype(np.float32)
        if lap is not None:
            lap("predict")
        # the field chain's lines: innermost rise, LMedS + Tukey, support and shift gates
        lines, seen, _, support, _ = robust_edge_lines(
            sub, np.array([u0, v0], float), self.camera, corners_pred,
            self._line_params(hw, tp.shift_fraction * hw))
        if lap is not None:
            lap("edges")
        return lines, seen, support

    def _track(self, img: np.ndarray, k: int, timings: dict) -> TrackResult | str:
        t = time.perf_counter()

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            timings[name] = timings.get(name, 0.0) + (now - t) * 1e3
            t = now

        tp = self.tp
        n = len(self._model_mm)
        pose = self._predict(k)
        self._follow_view(pose)
        # no velocity yet (second frame), or the first frame after a full measurement (its
        # offsets are new; one edge may still sit ~2-3 px off a worn holder's model): a
        # wider band, and its wider centring limit
        cold = self._vel is None or self._after_full
        hw = tp.band_half_width_px * (tp.cold_band_factor if cold else 1.0)
        passes = dropped = 0
        for _ in range(tp.max_passes):
            passes += 1
            found_at = self._lines_at(img, pose, hw, lap)
            if isinstance(found_at, str):
                return found_at
            lines, seen, support = found_at
            # an edge whose offset no anchor has measured yet (hidden then) has only the
            # others' median offset, millimetres off on a worn holder: its position counts as
            # far as the measured offsets agree (:meth:`_weigh_unmeasured`), its direction in
            # full; the next anchor measures it
            found, lines_found = seen, lines
            new = seen & ~self._measured if self._measured is not None else None
            fam = np.bincount(np.arange(n)[seen] % 2, minlength=2)
            if seen.sum() < tp.lines_needed(n) or fam.min() < 2:
                worst = int(np.argmin(support))
                return (f"only {int(seen.sum())} of {n} edges seen (< {tp.lines_needed(n)}, or < 2 "
                        f"per direction; least-supported edge {worst}: "
                        f"{100 * support[worst]:.0f} % of it): jump, occlusion or lost edges")
            out = self._fit_without_outliers(pose, lines, seen, new)
            if isinstance(out, str):
                return out
            (pose, r, r_start, J, J2), lines, seen, d = out
            dropped += d
            lap("solve")
            # how far the fit moved the bands' centres (the model's edges, along their
            # normals): profiles sampled off-centre cut a rise at the band's end (a biased
            # edge), so once more, centred on the fitted pose. Not how far the edges lie from
            # the model: a worn edge whose break varies along it lies a few px off the rigid
            # model however the bands are centred (the residual checks judge that)
            moved = bands_moved_px(r_start, r)
            if moved <= tp.centred_fraction * hw:
                break
        else:
            return (f"the bands did not settle: the pose fit moved the edges by {moved:.1f} px "
                    f"on the last of {tp.max_passes} passes (> "
                    f"{tp.centred_fraction * hw:.1f} px): the prediction is too far off")
        why = self._check(pose, r, J, J2, seen, new)
        if isinstance(why, str):
            return why
        rms, std = why
        lap("check")
        X = intersect_consecutive(np.where(np.isfinite(lines), lines, 0.0))
        corners_ideal = np.roll(X, 1, axis=0)   # corner i: edges i - 1 and i
        visible = seen & np.roll(seen, 1)
        corners_px = np.full((n, 2), np.nan)
        corners_px[visible] = self.camera.distort_px(corners_ideal[visible])
        res = TrackResult(k, "track", pose, std, True, "", rms_px=rms,
                          edge_support=float(support[seen].min()), corners_px=corners_px,
                          lines_seen=int(seen.sum()), corners_used=int(visible.sum()),
                          lines_dropped=dropped, lines_ideal=lines, edges_used=seen,
                          lines_found=lines_found, edges_found=found)
        res.passes = passes
        return res

    def _fit_without_outliers(self, start: Pose, lines: np.ndarray, seen: np.ndarray,
                              new: np.ndarray | None):
        """The pose fitted to the seen lines from ``start`` (:meth:`_fit_lines_pose`); a line
        far off the rigid model while the others fit rests on something else (a lump's
        outline, the cutter, the wrong rise): it is left out and the pose fitted again, up to
        ``max_dropped_lines`` times. Returns ``(fit, lines, seen, dropped)`` or a reason."""
        tp = self.tp
        n = len(self._model_mm)
        dropped = 0
        for _ in range(tp.max_dropped_lines + 1):
            fit = self._fit_lines_pose(start, lines, seen, new)
            if isinstance(fit, str):
                return fit
            r = fit[1]
            ks = np.nonzero(seen)[0]
            misfit = np.maximum(np.abs(r[:len(ks)]), np.abs(r[len(ks):]))
            worst = int(np.argmax(misfit))
            bar = max(tp.line_outlier_px, tp.line_outlier_factor * float(np.median(misfit)))
            if misfit[worst] <= bar or seen.sum() <= tp.lines_needed(n):
                break
            seen = seen.copy()
            seen[ks[worst]] = False
            lines = lines.copy()
            lines[ks[worst]] = np.nan
            dropped += 1
        return fit, lines, seen, dropped

    def _fit_lines_pose(self, pose: Pose, lines: np.ndarray, seen: np.ndarray,
                        new: np.ndarray | None = None, iterations: int = 8):
        """Gauss-Newton on the model-to-line distances: for every seen edge ``k`` (from model
        corner ``k`` to ``k + 1``), the signed distances of both projected ends to the edge's
        line (ideal px); edges not seen are left out, so that a corner whose other edge is
        hidden still counts through its seen one (Drummond & Cipolla 2002: distances along
        the edge normals). Parameters: the six DOFs. ``new``: the edges whose offsets were not
        measured (:meth:`_weigh_unmeasured`). Returns the pose, the residuals at the end
        (weighted) and at the start (each (2 m,)) and the final Jacobian (2 m, 6), or a
        reason."""
        n = len(self._model_mm)
        ks = np.nonzero(seen)[0]
        rows = np.concatenate([ks, n + ks])        # of the ends (P_k, P_k+1) of all edges
        L = np.concatenate([lines[ks], lines[ks]])
        Pe = self._ends_mm[rows]
        sel = np.nonzero(new[ks])[0] if new is not None else np.zeros(0, int)

        def residuals(ps: Pose):
            X = ps.apply(Pe)
            if np.any(X[:, 2] <= 0):
                return None
            uv = X[:, :2] / X[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]
            return L[:, 0] * uv[:, 0] + L[:, 1] * uv[:, 1] + L[:, 2]

        r = residuals(pose)
        if r is None:
            return "the predicted holder is behind the camera"
        # where the edges lie from the bands' centres (an unmeasured edge's position as far as
        # it is known)
        r0 = self._weigh_unmeasured(pose, ks, sel, L, r)[0] if len(sel) else r
        dof = pose.dof
        for _ in range(iterations):
            J2 = self._end_jacobian(pose)
            J = L[:, 0:1] * J2[0::2][rows] + L[:, 1:2] * J2[1::2][rows]
            if len(sel):
                r, J = self._weigh_unmeasured(pose, ks, sel, L, r, J)
            try:
                step = np.linalg.lstsq(J, -r, rcond=None)[0]
            except np.linalg.LinAlgError:
                return "the pose fit failed: singular normal equations"
            dof = dof + step
            try:
                pose = Pose.from_euler(*dof)
            except InputError as e:
                return f"the pose fit failed: {e}"
            r = residuals(pose)
            if r is None:
                return "the fitted holder is behind the camera"
            # converged: the last step is far below the std (>= ~0.005 mm / deg here)
            if np.all(np.abs(step) < 1e-4):
                break
        if len(sel):
            r = self._weigh_unmeasured(pose, ks, sel, L, r, J)[0]
        # the Jacobian of the last step (its pose differs from the result by < 1e-4)
        return pose, r, r0, J, J2

    def _weigh_unmeasured(self, pose: Pose, ks: np.ndarray, sel: np.ndarray, L: np.ndarray,
                          r: np.ndarray, J: np.ndarray | None = None) -> tuple:
        """Residuals and Jacobian rows (start rows, then end rows, of the edges ``ks``) with
        the edges ``ks[sel]``, whose offsets no anchor has measured, weighted as edges with
        an unknown offset ``o`` of prior std ``s_o`` (the measured edges' spread about their
        median, which the unmeasured ones carry): ``o`` moves the pair of end residuals along
        ``g`` (their derivatives w.r.t. ``o``), so that component gets the weight
        ``sqrt(s^2 / (s^2 + |g|^2 s_o^2))`` (``s``: ``LINE_SCALE_PX``, a tracked line's
        scatter about the model) and the orthogonal one, the edge's direction, the weight 1. Equal
        offsets (a uniform break) keep the edge's position; a worn holder's, which differ
        by millimetres, keep its direction only."""
        m = len(ks)
        i = np.concatenate([sel, sel + m])
        k = np.concatenate([ks[sel], ks[sel]])
        ends = self._ends_mm[np.concatenate([ks[sel], len(self._model_mm) + ks[sel]]), :2]
        g = offset_slope(pose, ends, self.holder.edge_normals[k], L[i], self.K)[1]
        q = len(sel)
        gs, ge = g[:q], g[q:]
        gn = np.hypot(gs, ge)
        us, ue = gs / gn, ge / gn
        s2 = LINE_SCALE_PX ** 2
        c = 1.0 - np.sqrt(s2 / (s2 + gn ** 2 * self._offset_spread_mm ** 2))
        r = r.copy()
        a, b = sel, sel + m
        pr = us * r[a] + ue * r[b]
        r[a] -= c * us * pr
        r[b] -= c * ue * pr
        if J is None:
            return r, None
        J = J.copy()
        pj = us[:, None] * J[a] + ue[:, None] * J[b]
        J[a] -= (c * us)[:, None] * pj
        J[b] -= (c * ue)[:, None] * pj
        return r, J

    def _end_jacobian(self, pose: Pose) -> np.ndarray:
        """Pixel Jacobian (80, 6) of both ends of every edge (``P_k``, then ``P_k+1``)."""
        return pixel_jacobian(pose.R, pose.t_mm, self._ends_mm, self.K)[0]

    def _check(self, pose: Pose, r: np.ndarray, J: np.ndarray, J2: np.ndarray,
               seen: np.ndarray, new: np.ndarray | None = None):
        """The checks of a tracked pose (module doc, step 4) on the model-to-line distances
        ``r`` (Jacobian ``J`` w.r.t. the DOFs): ``(rms_px, std_dof)`` when it passes, else
        the reason. The std is the Gauss-Newton covariance ``s^2 (J^T J)^-1``."""
        tp = self.tp
        rms = float(np.sqrt(np.mean(r ** 2)))
        # the limits follow the residual of the last full measurement (broken edges image
        # off the rigid model by a share of their width that varies along the contour: a
        # residual of the holder, not of the tracking)
        rms_max = max(tp.max_rms_px, tp.rms_ref_factor * self._rms_ref)
        res_max = max(tp.max_corner_residual_px, 2.5 * rms_max)
        if rms > rms_max:
            return (f"model-to-edge RMS {rms:.2f} px > {rms_max:.2f} px: the tracked edges do "
                    "not fit the holder")
        ks = np.nonzero(seen)[0]
        j = int(np.argmax(np.abs(r)))
        if abs(r[j]) > res_max:
            return (f"an end of edge {ks[j % len(ks)]} is {abs(r[j]):.2f} px off its line "
                    f"(> {res_max:.2f} px)")
        s2 = float(r @ r) / max(r.size - 6, 1)
        std = np.sqrt(np.clip(np.diag(s2 * np.linalg.inv(J.T @ J)), 0, None))
        # the edges left out cost information: a DOF that the seen edges pin down much worse
        # than all of them would (a short edge family lost, far away) is not the full
        # measurement's accuracy, so the frame is measured in full
        ratio = self._std_ratio(pose, seen, J2, new)
        j = int(np.argmax(ratio))
        if ratio[j] > tp.max_std_ratio:
            return (f"the {int(seen.sum())} edges seen fix {DOF_NAMES[j]} {ratio[j]:.1f}x less "
                    f"well than all {len(seen)} (> {tp.max_std_ratio}): too few edges")
        return rms, std

    def _std_ratio(self, pose: Pose, seen: np.ndarray, J2: np.ndarray,
                   new: np.ndarray | None = None) -> np.ndarray:
        """Per DOF, the std from the seen edges over the std from all edges (same noise):
        ``sqrt(diag((J_s^T J_s)^-1) / diag((J^T J)^-1))`` with ``J`` the model-to-line
        distances' Jacobian (``J2``: :meth:`_end_jacobian`), the lines the model's edges
        projected with ``pose``."""
        ideal = self._project(pose)
        d = np.roll(ideal, -1, axis=0) - ideal
        nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
        nrm = np.concatenate([nrm, nrm])
        J = nrm[:, 0:1] * J2[0::2] + nrm[:, 1:2] * J2[1::2]      # rows: edge k's two ends
        use = np.concatenate([seen, seen])
        Ju = J[use]
        ks = np.nonzero(seen)[0]
        if new is not None and new[ks].any():   # weighted as in the fit
            L = np.column_stack([nrm, np.zeros(len(nrm))])[np.concatenate([ks, ks + len(seen)])]
            Ju = self._weigh_unmeasured(pose, ks, np.nonzero(new[ks])[0], L,
                                        np.zeros(len(Ju)), Ju)[1]
        with np.errstate(invalid="ignore"):
            return np.sqrt(np.diag(np.linalg.inv(Ju.T @ Ju))
                           / np.diag(np.linalg.inv(J.T @ J)))
