"""Pictures of a camera calibration: an overlay per image and the coverage map.

* :func:`draw_target_overlay`: the image with every point found, coloured along its order
  (blue = first id, red = last), consecutive ids joined, id 0 ringed and labelled, a few
  other ids written, and the residuals (projected - measured) drawn magnified;
* :func:`plot_coverage`: all points of all used images over the image frame, one colour per
  image (where the field is covered decides how well distortion is determined), beside the
  residual vectors magnified (a pattern in them shows a model that does not fit);
* :func:`write_calibration_pictures`: both for a :class:`.intrinsics.CalibrationResult`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["draw_target_overlay", "plot_coverage", "write_calibration_pictures"]


def _colour(frac: float) -> tuple[int, int, int]:
    """BGR from blue (0) through green to red (1)."""
    f = float(np.clip(frac, 0.0, 1.0))
    return (int(255 * (1 - f)), int(255 * (1 - abs(2 * f - 1))), int(255 * f))


def draw_target_overlay(gray: np.ndarray, points_px, ids, n_points: int, *, residuals_px=None,
                        residual_scale: float | None = None, title: str = "") -> np.ndarray:
    """BGR overlay of one image's target points (module docstring)."""
    import cv2

    img = cv2.cvtColor(np.asarray(gray, np.uint8), cv2.COLOR_GRAY2BGR) if np.ndim(gray) == 2 \
        else np.array(gray, np.uint8)
    h, w = img.shape[:2]
    up = 2 if max(h, w) < 1000 else 1  # small images: draw at twice the size, readable text
    if up > 1:
        img = cv2.resize(img, (w * up, h * up), interpolation=cv2.INTER_NEAREST)
    pts = np.asarray(points_px, float).reshape(-1, 2)
    ids = np.asarray(ids, int).ravel()
    order = np.argsort(ids)
    pts, ids = pts[order], ids[order]
    P = (pts + 0.5) * up - 0.5
    lw = max(1, round(max(h, w) * up / 1500))
    r = max(3, round(max(h, w) * up / 400))
    frac = ids / max(n_points - 1, 1)
    for k in range(len(ids) - 1):
        if ids[k + 1] == ids[k] + 1:
            a, b = P[k].round().astype(int), P[k + 1].round().astype(int)
            cv2.line(img, tuple(a), tuple(b), _colour(frac[k]), lw, cv2.LINE_AA)
    step = 1 if len(ids) <= 40 else max(1, len(ids) // 12)
    font = 0.35 * up * max(1.0, max(h, w) / 1000)
    for k, (p, i) in enumerate(zip(P, ids)):
        c = tuple(p.round().astype(int))
        cv2.circle(img, c, r, _colour(frac[k]), lw, cv2.LINE_AA)
        if i == 0:
            cv2.circle(img, c, 3 * r, (0, 255, 255), 2 * lw, cv2.LINE_AA)
        if i == 0 or k % step == 0 or k == len(ids) - 1:
            _label(img, str(i), (c[0] + r + 2, c[1] - r - 2), font, lw,
                   (0, 255, 255) if i == 0 else (255, 255, 255))
    if residuals_px is not None:
        res = np.asarray(residuals_px, float).reshape(-1, 2)[order]
        scale = residual_scale or _residual_scale(res, max(h, w))
        for p, d in zip(P, res):
            q = p + d * scale * up
            cv2.arrowedLine(img, tuple(p.round().astype(int)), tuple(q.round().astype(int)),
                            (0, 0, 255), lw, cv2.LINE_AA, tipLength=0.3)
        title = f"{title}  residuals x{scale:.0f}".strip()
    if title:
        _label(img, title, (8 * up, 20 * up), 0.5 * up * max(1.0, max(h, w) / 1000), lw,
               (0, 255, 255))
    return img


def _label(img, text: str, org, scale: float, thickness: int, colour) -> None:
    """Text on a dark box, readable on any background."""
    import cv2

    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    x, y = int(org[0]), int(org[1])
    cv2.rectangle(img, (x - 2, y - th - 2), (x + tw + 2, y + base), (0, 0, 0), cv2.FILLED)
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness,
                cv2.LINE_AA)


def _residual_scale(res: np.ndarray, size_px: float) -> float:
    """A round magnification that makes the largest residual ~3 % of the image."""
    m = float(np.max(np.linalg.norm(res, axis=1))) if len(res) else 0.0
    if m <= 0:
        return 1.0
    raw = 0.03 * size_px / m
    p = 10 ** np.floor(np.log10(raw))
    return float(max(p * max(v for v in (1, 2, 5) if v * p <= raw), 1.0))


def plot_coverage(views: list, image_size_px, path, *, title: str = "") -> None:
    """Coverage map and residual vectors of all used images, written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = image_size_px
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8 * h / w + 0.8), constrained_layout=True)
    cmap = plt.get_cmap("tab20")
    all_res = np.concatenate([v["residuals_px"] for v in views]) if views else np.zeros((0, 2))
    scale = _residual_scale(all_res, max(w, h))
    for k, v in enumerate(views):
        p = np.asarray(v["points_px"], float)
        axes[0].scatter(p[:, 0], p[:, 1], s=6, color=cmap(k % 20), label=v["name"])
        r = np.asarray(v["residuals_px"], float)
        axes[1].quiver(p[:, 0], p[:, 1], r[:, 0] * scale, r[:, 1] * scale, angles="xy",
                       scale_units="xy", scale=1, width=0.002, color=cmap(k % 20))
    n = sum(len(v["ids"]) for v in views)
    axes[0].set_title(f"coverage: {n} points in {len(views)} images")
    axes[1].set_title(f"residuals (projected - measured) x{scale:.0f}")
    for ax in axes:
        ax.add_patch(plt.Rectangle((-0.5, -0.5), w, h, fill=False, color="k", lw=1))
        ax.set_xlim(-0.02 * w, 1.02 * w)
        ax.set_ylim(1.02 * h, -0.02 * h)
        ax.set_aspect("equal")
        ax.set_xlabel("u (px)")
    axes[0].set_ylabel("v (px)")
    if len(views) <= 20:
        axes[0].legend(fontsize=6, loc="center left", bbox_to_anchor=(1.0, 0.5), frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_calibration_pictures(result, image_paths, target, overlay_dir=None,
                               coverage_path=None) -> dict:
    """An overlay per used image (in ``overlay_dir``, named as the image with ``.png``) and the
    coverage map; returns ``{"overlays": [...], "coverage": path}`` of the files written."""
    import cv2

    out = {"overlays": [], "coverage": None}
    by_name = {}
    for p in image_paths:
        by_name.setdefault(Path(p).name, Path(p))
        by_name.setdefault(str(p), Path(p))
    if overlay_dir is not None and result.views:
        folder = Path(overlay_dir)
        folder.mkdir(parents=True, exist_ok=True)
        for v in result.views:
            src = by_name.get(v["name"])
            gray = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE) if src is not None else None
            if gray is None:
                continue
            rms = float(np.sqrt(np.mean(np.sum(v["residuals_px"] ** 2, axis=1))))
            amb = v["rotation_ambiguity_deg"]
            title = (f"{v['name']}: {len(v['ids'])} points, RMS {rms:.3f} px"
                     + (f", order up to {amb} deg" if amb else ""))
            img = draw_target_overlay(gray, v["points_px"], v["ids"], target.n_points,
                                      residuals_px=v["residuals_px"], title=title)
            dst = folder / (Path(v["name"]).stem + ".png")
            cv2.imwrite(str(dst), img)
            out["overlays"].append(str(dst))
    if coverage_path is not None and result.views:
        plot_coverage(result.views, result.image_size_px or result.camera.image_size_px,
                      coverage_path, title=f"{result.target} ({result.model} model), RMS "
                      f"{result.rms_px:.3f} px")
        out["coverage"] = str(coverage_path)
    return out
