"""Overlay image of a measurement: what was detected and what the pose predicts.

Drawn on the image (reduced to ``width_px`` and cropped around the holder): the inside contour
(grey), the characteristic segments (alternating green/cyan), the gradient edge points (yellow,
thinned), the detected corners (red circles, index 0 marked), the holder model projected at the
estimated pose (magenta: inner contour and outer rectangle), for ``dm+b`` each edge segment's
design-edge point with a tick across the measured band (white: used, red: down-weighted), and
the pose with its standard deviations and the quality verdict in text.

Convention:
    Input points are observed full-image pixels; drawing uses ``cv2`` fixed-point coordinates
    (``shift`` bits) so that sub-pixel positions survive the reduction.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import cv2
import numpy as np

from .errors import ImageError
from .geometry.camera import Camera
from .geometry.holder import Holder

__all__ = ["draw_overlay", "write_overlay"]

_SHIFT = 4


def _pts(p, scale, origin):
    q = (np.asarray(p, float) - origin) * scale
    return np.rint(q * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2)


def draw_overlay(image: np.ndarray, measurement, camera: Camera, holder: Holder,
                 width_px: int = 1000, crop: bool = True) -> np.ndarray:
    """BGR overlay image (see module doc)."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    h, w = img.shape[:2]
    origin = np.zeros(2)
    feats = measurement.features
    pose = measurement.pose
    pts_all = []
    if feats is not None:
        pts_all.append(feats.contour_px)
    if pose is not None:
        pts_all.append(camera.project(pose.apply(np.column_stack(
            [holder.outer_rectangle_mm, np.zeros(4)]))))
    if crop and pts_all:
        P = np.vstack([p for p in pts_all if np.all(np.isfinite(p))] or [np.zeros((1, 2))])
        pad = 0.08 * max(w, h)
        u0, v0 = np.clip(np.floor(P.min(axis=0) - pad), 0, None).astype(int)
        u1 = int(min(np.ceil(P[:, 0].max() + pad), w))
        v1 = int(min(np.ceil(P[:, 1].max() + pad), h))
        img = img[v0:v1, u0:u1]
        origin = np.array([u0, v0], float)
    scale = min(1.0, width_px / img.shape[1])
    out = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    # darken slightly so that the drawing stands out
    out = (out * 0.8).astype(np.uint8)
    aa = cv2.LINE_AA
    if feats is not None:
        cv2.polylines(out, [_pts(feats.contour_px, scale, origin)], True, (150, 150, 150), 1,
                      aa, _SHIFT)
        for k, s in enumerate(feats.segments):
            col = (0, 220, 0) if k % 2 == 0 else (220, 220, 0)
            pts = camera.distort_px(s.points_ideal_px)
            cv2.polylines(out, [_pts(pts, scale, origin)], False, col, 2, aa, _SHIFT)
        for e in feats.edge_points_px:
            for p in _pts(e[::8], scale, origin):
                cv2.circle(out, tuple(p[0]), 1 << _SHIFT, (0, 230, 255), -1, aa, _SHIFT)
    if pose is not None:
        inner = camera.project(pose.apply(holder.points_holder_mm))
        outer = camera.project(pose.apply(np.column_stack([holder.outer_rectangle_mm,
                                                           np.zeros(4)])))
        for poly in (inner, outer):
            if np.all(np.isfinite(poly)):
                cv2.polylines(out, [_pts(poly, scale, origin)], True, (255, 0, 255), 1, aa,
                              _SHIFT)
    band = measurement.edge_band
    if band is not None:
        # dm+b: each segment's design-edge point with a tick across the band (its measured
        # width: the radius times px per mm), white = used, red = down-weighted or not used
        bp = band.fit.profiles
        q = band.fit.design_points_px()
        ok = np.isfinite(q).all(axis=1)
        width = np.nan_to_num(band.fit.best.radius_mm * bp.px_per_mm)
        ends = q + (width[:, None] + 2.0) * bp.normals_ideal
        used = band.weights > 0.5
        for a, b, u in zip(q[ok], ends[ok], used[ok]):
            pa, pb = _pts(camera.distort_px(np.vstack([a, b])), scale, origin)
            col = (255, 255, 255) if u else (0, 0, 255)
            cv2.line(out, tuple(pa[0]), tuple(pb[0]), col, 1, aa, _SHIFT)
            cv2.circle(out, tuple(pa[0]), 2 << _SHIFT, col, -1, aa, _SHIFT)
    if measurement.corners_px is not None:
        for k, p in enumerate(_pts(measurement.corners_px, scale, origin)):
            cv2.circle(out, tuple(p[0]), 5 << _SHIFT, (0, 0, 255), 2 if k == 0 else 1, aa,
                       _SHIFT)
    _text(out, _lines(measurement))
    return out


def _lines(m) -> list[str]:
    q = m.quality
    # the verdict first, as `cutterpose measure` prints it
    lines = [f"ACCEPTED (method {m.method})"] if q.ok else textwrap.wrap(
        f"REFUSED: {q.reason} (method {m.method})", 90, subsequent_indent="  ")
    # long summary lines (the band's) wrapped to the overlay's width, not cut at its edge
    for line in m.pose_lines():
        lines += textwrap.wrap(line, 90, subsequent_indent="  ") or [""]
    return lines[:10]


def _text(img, lines):
    y = 22
    if lines:
        width = max(cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, 0.55, 1)[0][0] for t in lines)
        cv2.rectangle(img, (4, 4), (16 + width, 12 + 22 * len(lines)), (0, 0, 0), -1)
    for line in lines:
        cv2.putText(img, line, (10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1,
                    cv2.LINE_AA)
        y += 22


def write_overlay(image: np.ndarray, measurement, camera: Camera, holder: Holder, path,
                  width_px: int = 1000) -> Path:
    """Write :func:`draw_overlay` as a PNG (maximum compression)."""
    path = Path(path)
    out = draw_overlay(image, measurement, camera, holder, width_px)
    if not cv2.imwrite(str(path), out, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise ImageError(f"{path}: could not write the overlay (unknown extension or "
                         "unwritable folder)")
    return path
