"""Square-based targets: OpenCV's chessboard and ChArUco board.

``chessboard:COLSxROWS:SQUARE_MM``: COLS x ROWS inner corners (OpenCV's pattern size), object
points ``(j * s, i * s, 0)`` in ``findChessboardCornersSB``'s row-by-row order. The square
between corners 0, 1, COLS and COLS + 1 is black (so are the board's corner squares, as in
OpenCV's printed pattern); when COLS + ROWS is odd this fixes the order, otherwise the board is
symmetric and the order is known up to 180 deg (90 deg for some square boards).

``charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT``: ``cv2.aruco.CharucoBoard`` with COLS x ROWS
squares and the named dictionary (``DICT_5X5_100`` or ``5x5_100``, ``APRILTAG_36h11``, ...);
object points are the board's chessboard corners (``getChessboardCorners``: origin at the
board's outer corner, first corner at ``(s, s)``), ids are OpenCV's corner ids. Partial views
give the corners seen; the markers make the order unique.

References:
    OpenCV calib3d ``findChessboardCornersSB`` (Duda & Frese, "Accurate detection and
    localization of checkerboard corners for calibration", BMVC 2018); OpenCV objdetect
    ``aruco::CharucoDetector``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ImageError, InputError
from .circle_detect import sample_gray, to_gray_u8
from .targets import (
    Target,
    TargetDetection,
    choose_order,
    description_fields,
    no_more_modifiers,
    parse_grid_size,
    positive_number,
    register_target,
    symmetry_permutations,
)

__all__ = ["ChessboardTarget", "CharucoTarget", "aruco_dictionary"]


def _ramp(d, blur_mm):
    """Coverage of the side d < 0 of an edge, anti-aliased over one footprint."""
    return np.clip(0.5 - d / np.maximum(blur_mm, 1e-9), 0.0, 1.0)


@register_target
@dataclass(frozen=True)
class ChessboardTarget(Target):
    """OpenCV's chessboard (module docstring)."""

    cols: int
    rows: int
    square_mm: float
    kind = "chessboard"

    def __post_init__(self):
        if self.cols < 2 or self.rows < 2:
            raise InputError(f"chessboard target: at least 2x2 inner corners, got "
                             f"{self.cols}x{self.rows}")

    @property
    def points_target_mm(self) -> np.ndarray:
        i, j = np.mgrid[0:self.rows, 0:self.cols]
        s = self.square_mm
        return np.stack([j.ravel() * s, i.ravel() * s, 0.0 * i.ravel()], 1).astype(float)

    @property
    def rotation_symmetry_deg(self) -> int:
        if (self.cols + self.rows) % 2:
            return 0
        return 90 if self.cols == self.rows and self.cols % 2 == 0 else 180

    # --- rendering: squares from -s to cols*s (rows*s), a white margin of one square -------
    @property
    def bounds_mm(self):
        s = self.square_mm
        return (-2 * s, (self.cols + 1) * s, -2 * s, (self.rows + 1) * s)

    def darkness(self, x_mm, y_mm, blur_mm):
        s = self.square_mm
        x, y = np.asarray(x_mm, float), np.asarray(y_mm, float)

        def wave(t):  # +1 on even squares, -1 on odd, ramped over the footprint at lines
            k = np.floor(t / s)
            sign = np.where(k % 2 == 0, 1.0, -1.0)
            dist = np.minimum(t - k * s, (k + 1) * s - t)
            return sign * np.clip(2.0 * dist / np.maximum(blur_mm, 1e-9), 0.0, 1.0)

        check = 0.5 + 0.5 * wave(x) * wave(y)
        d_board = np.maximum.reduce([-s - x, x - self.cols * s, -s - y, y - self.rows * s])
        return check * _ramp(d_board, blur_mm)

    # --- detection ----------------------------------------------------------------------------
    def detect(self, gray) -> TargetDetection:
        import cv2

        try:
            g = to_gray_u8(gray)
        except ImageError as e:
            return TargetDetection.missing(str(e))
        corners = _find_chessboard(g, (self.cols, self.rows))
        if corners is None:
            return TargetDetection.missing(f"{self.cols}x{self.rows} chessboard not found")
        pts = corners.reshape(-1, 2).astype(float)
        obj = self.points_target_mm
        s = self.square_mm
        probes = np.array([[0.5 * s, 0.5 * s], [1.5 * s, 0.5 * s], [0.5 * s, 1.5 * s],
                           [1.5 * s, 1.5 * s]])

        def score(ids):  # black first square: (white - black) / (white + black)
            H, _ = cv2.findHomography(obj[ids][:, :2], pts, 0)
            q = np.c_[probes, np.ones(4)] @ H.T
            v = sample_gray(g, q[:, :2] / q[:, 2:])
            dark, light = v[0] + v[3], v[1] + v[2]
            return float((light - dark) / max(light + dark, 1e-9))

        perms = symmetry_permutations(obj[:, :2])
        ids, amb, why = choose_order(obj, pts, perms, score, 0.1)
        if ids is None:
            return TargetDetection.missing(f"chessboard order: {why}")
        return TargetDetection(pts, ids, amb)

    # --- description --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"kind": self.kind, "cols": self.cols, "rows": self.rows,
                "square_mm": self.square_mm}

    @classmethod
    def from_dict(cls, d, where="target"):
        with description_fields(where):
            return cls(int(d["cols"]), int(d["rows"]), positive_number(d["square_mm"], "square_mm"))

    @classmethod
    def from_spec(cls, fields, options):
        if len(fields) != 2:
            raise InputError("chessboard target: give chessboard:COLSxROWS:SQUARE_MM with the "
                             "inner corners (e.g. chessboard:9x6:25)")
        cols, rows = parse_grid_size(fields[0], "chessboard target")
        no_more_modifiers(dict(options), "chessboard")
        return cls(cols, rows, positive_number(fields[1], "chessboard square"))

    def spec(self) -> str:
        return f"{self.kind}:{self.cols}x{self.rows}:{self.square_mm:g}"


def _find_chessboard(gray: np.ndarray, pattern, max_side: int = 1600):
    """Inner corners (N, 1, 2) in OpenCV's order, or None.

    ``findChessboardCornersSB`` (``CALIB_CB_NORMALIZE_IMAGE`` only as a fallback, its
    histogram equalisation moves corners by ~0.03 px) on a copy of at
    most ``max_side`` pixels, then ``cv2.cornerSubPix`` at full resolution (below). The
    classic ``findChessboardCorners`` is the last resort.
    """
    import cv2

    h, w = gray.shape
    scale = min(1.0, max_side / max(h, w))
    small = gray if scale == 1.0 else cv2.resize(gray, (round(w * scale), round(h * scale)),
                                                 interpolation=cv2.INTER_AREA)
    found, corners = False, None
    # plain first (a failed search with CALIB_CB_ACCURACY costs seconds; cornerSubPix below
    # refines as well); the slow exhaustive search only when OpenCV's quick check sees a board
    tries = [0, cv2.CALIB_CB_NORMALIZE_IMAGE]
    if cv2.checkChessboard(small, pattern):
        tries += [cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY,
                  cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE]
    for flags in tries:
        found, corners = cv2.findChessboardCornersSB(small, pattern, flags=flags)
        if found:
            break
    if not found:
        found, corners = cv2.findChessboardCorners(
            small, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
    if corners is None or len(corners) != pattern[0] * pattern[1]:
        return None
    corners = ((corners.astype(np.float64) + 0.5) / scale - 0.5).astype(np.float32)
    # cornerSubPix in a window of 0.8 of the shortest square side (half-size 0.4), which
    # reaches no other corner: on rendered boards it halves the corners' RMS error of SB's
    # own sub-pixel step (0.03-0.1 px -> 0.03-0.06 px at 20-40 px per square)
    c = corners.reshape(pattern[1], pattern[0], 2)
    steps = np.concatenate([np.linalg.norm(np.diff(c, axis=1), axis=-1).ravel(),
                            np.linalg.norm(np.diff(c, axis=0), axis=-1).ravel()])
    win = int(np.clip(0.4 * np.percentile(steps, 5), 2, 30))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (win, win), (-1, -1), crit)
    return corners


def aruco_dictionary(name: str):
    """``cv2.aruco`` predefined dictionary by name (``DICT_5X5_100``, ``5x5_100``, ...)."""
    import cv2

    key = str(name).strip().upper()
    key = key if key.startswith("DICT_") else "DICT_" + key
    if not hasattr(cv2.aruco, key):
        known = sorted(n[5:] for n in dir(cv2.aruco) if n.startswith("DICT_") and n.isupper())
        raise InputError(f"unknown ArUco dictionary {name!r}; known: {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


@register_target
@dataclass(frozen=True)
class CharucoTarget(Target):
    """OpenCV's ChArUco board (module docstring)."""

    cols: int
    rows: int
    square_mm: float
    marker_mm: float
    dictionary: str = "DICT_5X5_100"
    kind = "charuco"
    min_points = 6

    def __post_init__(self):
        if self.cols < 2 or self.rows < 2:
            raise InputError(f"charuco target: at least 2x2 squares, got {self.cols}x{self.rows}")
        if not 0 < self.marker_mm < self.square_mm:
            raise InputError("charuco target: the marker must be smaller than the square")
        d = str(self.dictionary).upper()
        object.__setattr__(self, "dictionary", d if d.startswith("DICT_") else "DICT_" + d)
        aruco_dictionary(self.dictionary)  # fail early on an unknown name

    def board(self):
        import cv2

        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, self.marker_mm,
                                      aruco_dictionary(self.dictionary))

    @property
    def points_target_mm(self) -> np.ndarray:
        return np.asarray(self.board().getChessboardCorners(), float).reshape(-1, 3)

    @property
    def rotation_symmetry_deg(self) -> int:
        return 0

    # --- rendering: the board's own image as a texture, white margin of one square ---------
    @property
    def bounds_mm(self):
        s = self.square_mm
        return (-s, (self.cols + 1) * s, -s, (self.rows + 1) * s)

    _LEVELS = (8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256)  # texels per square

    def _texture(self, pps: int):
        """The board's image with ``pps`` texels per square, box-filtered from 256 per square
        (a mipmap level: each texel is the mean of what it covers)."""
        import cv2

        cache = self.__dict__.setdefault("_tex_cache", {})
        if pps not in cache:
            top = self._LEVELS[-1]
            if top not in cache:
                cache[top] = self.board().generateImage(
                    (self.cols * top, self.rows * top), marginSize=0,
                    borderBits=1).astype(np.float32) / 255.0
            cache[pps] = cache[top] if pps == top else cv2.resize(
                cache[top], (self.cols * pps, self.rows * pps), interpolation=cv2.INTER_AREA)
        return cache[pps]

    def darkness(self, x_mm, y_mm, blur_mm):
        """Ink of the board's own image (OpenCV's ``generateImage``), sampled bilinearly from
        the mipmap level whose texels are just below the pixel's footprint (anti-aliased)."""
        import cv2

        x, y = np.asarray(x_mm, float), np.asarray(y_mm, float)
        foot = np.broadcast_to(np.asarray(blur_mm, float), x.shape)
        levels = np.array(self._LEVELS)
        need = self.square_mm / np.maximum(foot, 1e-6)  # texels per square for 1 per footprint
        level = np.minimum(np.searchsorted(levels, need), len(levels) - 1)
        ink = np.zeros(x.shape)
        for li in np.unique(level):
            m = level == li
            pps = int(levels[li])
            sc = pps / self.square_mm
            tex = self._texture(pps)
            u, w = x[m] * sc - 0.5, y[m] * sc - 0.5
            n = len(u)
            rows = -(-n // 4096)  # cv2.remap wants maps below 32767 per side
            mu = np.zeros(rows * 4096, np.float32)
            mv = np.zeros(rows * 4096, np.float32)
            mu[:n], mv[:n] = u, w
            v = cv2.remap(tex, mu.reshape(rows, 4096), mv.reshape(rows, 4096),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
            ink[m] = 1.0 - v.ravel()[:n]
        s = self.square_mm
        d_board = np.maximum.reduce([-x, x - self.cols * s, -y, y - self.rows * s])
        return ink * _ramp(d_board, blur_mm)

    # --- detection ----------------------------------------------------------------------------
    def detect(self, gray) -> TargetDetection:
        import cv2

        try:
            g = to_gray_u8(gray)
        except ImageError as e:
            return TargetDetection.missing(str(e))
        try:
            corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(self.board()).detectBoard(g)
        except cv2.error as e:
            return TargetDetection.missing(f"charuco detector failed ({e.err})")
        n = 0 if ids is None else len(ids)
        if n < self.min_points:
            nm = 0 if marker_ids is None else len(marker_ids)
            return TargetDetection.missing(f"charuco board: {n} corners found ({nm} markers), "
                                           f"need {self.min_points}")
        return TargetDetection(corners.reshape(-1, 2).astype(float), ids.ravel(), 0,
                               info={"markers": int(len(marker_ids))})

    # --- description --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"kind": self.kind, "cols": self.cols, "rows": self.rows,
                "square_mm": self.square_mm, "marker_mm": self.marker_mm,
                "dictionary": self.dictionary}

    @classmethod
    def from_dict(cls, d, where="target"):
        with description_fields(where):
            return cls(int(d["cols"]), int(d["rows"]), float(d["square_mm"]),
                       float(d["marker_mm"]), str(d.get("dictionary", "DICT_5X5_100")))

    @classmethod
    def from_spec(cls, fields, options):
        if len(fields) != 4:
            raise InputError("charuco target: give charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT "
                             "with the squares (e.g. charuco:5x7:30:22:DICT_5X5_100)")
        cols, rows = parse_grid_size(fields[0], "charuco target")
        no_more_modifiers(dict(options), "charuco")
        return cls(cols, rows, positive_number(fields[1], "charuco square"),
                   positive_number(fields[2], "charuco marker"), fields[3])

    def spec(self) -> str:
        return (f"{self.kind}:{self.cols}x{self.rows}:{self.square_mm:g}:{self.marker_mm:g}:"
                f"{self.dictionary}")
