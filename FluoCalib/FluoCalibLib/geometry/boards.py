"""Calibration boards: spec strings, 3D corner layout, texture and detection.

Spec strings
------------
- ``chessboard:COLSxROWS:SQUARE_MM`` -- COLS x ROWS *inner* corners (OpenCV's
  ``patternSize``), e.g. ``chessboard:9x6:25``.
- ``charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT`` -- COLS x ROWS *squares*
  (OpenCV's ``CharucoBoard`` size), e.g. ``charuco:7x5:30:22:DICT_5X5_100``.

Board frame (mm, z = 0 on the board, z pointing away from the printed side
into the board so that a camera looking at the board sees z > 0 behind it):

- chessboard: origin at the first inner corner; corner (i, j) (column i, row j)
  at (i*s, j*s, 0); detection order row-major as ``cv2.findChessboardCorners``.
  The outer square diagonally beyond corner (0, 0) is black; detections are put
  in that canonical order (for boards whose COLS and ROWS differ in parity, the
  two ends of the diagonal differ in colour, so the 180-degree ambiguity of
  OpenCV's detector is resolved).
- charuco: OpenCV's frame, origin at the outer top-left corner of the board.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["Board", "parse_board", "Detection"]


@dataclass
class Detection:
    """Corners found in one image.

    Attributes
    ----------
    ids : (M,) int ndarray
        Indices into ``Board.object_points``.
    image_points : (M, 2) float ndarray
        Sub-pixel corner positions [px].
    """

    ids: np.ndarray
    image_points: np.ndarray


@dataclass(frozen=True)
class Board:
    """A planar calibration target.

    Use :func:`parse_board` to build one from a spec string.
    """

    kind: str
    cols: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = ""

    # ----------------------------------------------------------- geometry
    @property
    def spec(self):
        """The spec string this board was parsed from (canonical form)."""
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_mm:g}"
        return (f"charuco:{self.cols}x{self.rows}:{self.square_mm:g}:{self.marker_mm:g}:"
                f"{self.dictionary}")

    def _cv_board(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, self.marker_mm, d)

    @property
    def object_points(self):
        """(N, 3) corner positions in the board frame [mm], in detection-id order."""
        if self.kind == "chessboard":
            i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
            return np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * self.square_mm
        return np.asarray(self._cv_board().getChessboardCorners(), dtype=float).reshape(-1, 3)

    @property
    def n_corners(self):
        return len(self.object_points)

    @property
    def extent_mm(self):
        """(xmin, ymin, xmax, ymax) of the printed board area [mm]."""
        s = self.square_mm
        if self.kind == "chessboard":
            return (-s, -s, self.cols * s, self.rows * s)
        return (0.0, 0.0, self.cols * s, self.rows * s)

    def texture(self, px_per_mm=8.0):
        """Board image (uint8, white 255 / black 0) with a white margin of one square.

        Returns
        -------
        image : (H, W) uint8 ndarray
        origin_mm : (2,) ndarray
            Board coordinates of the *corner* of texture pixel (0, 0); pixel
            (c, r) covers board x in origin + [c, c+1] / px_per_mm.
        """
        s = self.square_mm
        x0, y0, x1, y1 = self.extent_mm
        m = s  # quiet zone so the outer squares have contrast on every side
        origin = np.array([x0 - m, y0 - m])
        w = int(round((x1 - x0 + 2 * m) * px_per_mm))
        h = int(round((y1 - y0 + 2 * m) * px_per_mm))
        if self.kind == "chessboard":
            yy, xx = np.mgrid[0:h, 0:w]
            bx = origin[0] + (xx + 0.5) / px_per_mm
            by = origin[1] + (yy + 0.5) / px_per_mm
            inside = (bx >= x0) & (bx < x1) & (by >= y0) & (by < y1)
            sq = (np.floor((bx - x0) / s) + np.floor((by - y0) / s)) % 2
            img = np.full((h, w), 255, np.uint8)
            img[inside & (sq == 0)] = 0  # square (0,0), beyond corner 0, is black
            return img, origin
        bw = int(round((x1 - x0) * px_per_mm))
        bh = int(round((y1 - y0) * px_per_mm))
        inner = self._cv_board().generateImage((bw, bh), marginSize=0, borderBits=1)
        img = np.full((h, w), 255, np.uint8)
        mp = int(round(m * px_per_mm))
        img[mp:mp + bh, mp:mp + bw] = inner
        return img, origin

    # ----------------------------------------------------------- detection
    def detect(self, gray, subpix_window=None):
        """Find the board's corners in a grayscale image.

        Parameters
        ----------
        gray : (H, W) uint8 ndarray
        subpix_window : int, optional
            Half size of the ``cornerSubPix`` window [px]; default scales with
            the square size in the image (OpenCV's samples use 11 for 9x6 boards
            on 640x480 images), at most 11.

        Returns
        -------
        Detection or None
            None when the board is not found (too few ChArUco corners: < 6).
        """
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise FluoInputError("detection needs a 2D uint8 grayscale image", field="image",
                                 value=(gray.shape, str(gray.dtype)))
        if self.kind == "chessboard":
            flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
            found, corners = cv2.findChessboardCorners(gray, (self.cols, self.rows), flags=flags)
            if not found:
                return None
            corners = corners.reshape(-1, 2).astype(np.float32)
            win = subpix_window or self._subpix_window(corners)
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-3)
            corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (win, win), (-1, -1), crit)
            pts = corners.reshape(-1, 2).astype(float)
            pts = self._canonical_order(gray, pts)
            return Detection(np.arange(len(pts)), pts)
        detector = cv2.aruco.CharucoDetector(self._cv_board())
        ch_corners, ch_ids, _, _ = detector.detectBoard(gray)
        if ch_ids is None or len(ch_ids) < 6:
            return None
        return Detection(ch_ids.ravel().astype(int), ch_corners.reshape(-1, 2).astype(float))

    def _subpix_window(self, corners):
        grid = corners.reshape(self.rows, self.cols, 2)
        step = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2))
        return int(max(3, min(11, step * 0.4)))

    def _canonical_order(self, gray, pts):
        """Reverse the corner list if OpenCV started at the white end of the diagonal."""
        if (self.cols % 2) == (self.rows % 2):
            return pts  # symmetric board: colours cannot tell the ends apart
        grid = pts.reshape(self.rows, self.cols, 2)

        def outer_square_value(c0, c_diag):
            centre = c0 + 0.5 * (c0 - c_diag)  # middle of the outer square beyond c0
            x, y = int(round(centre[0])), int(round(centre[1]))
            r = max(1, int(0.15 * np.linalg.norm(c0 - c_diag)))
            h, w = gray.shape
            if not (r <= x < w - r and r <= y < h - r):
                return np.nan
            return float(gray[y - r:y + r + 1, x - r:x + r + 1].mean())

        v_start = outer_square_value(grid[0, 0], grid[1, 1])
        v_end = outer_square_value(grid[-1, -1], grid[-2, -2])
        if np.isfinite(v_start) and np.isfinite(v_end) and v_start > v_end:
            return pts[::-1].copy()
        return pts


def parse_board(spec):
    """Parse a board spec string (see module docstring).

    Raises
    ------
    FluoInputError
        On any malformed part, naming the part.
    """
    if isinstance(spec, Board):
        return spec
    text = str(spec).strip()
    parts = text.split(":")
    kind = parts[0].lower()
    if kind not in ("chessboard", "charuco"):
        raise FluoInputError("board kind must be 'chessboard' or 'charuco'", field="board",
                             value=text)
    need = 3 if kind == "chessboard" else 5
    if len(parts) != need:
        form = ("chessboard:COLSxROWS:SQUARE_MM" if kind == "chessboard"
                else "charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT")
        raise FluoInputError(f"board spec must look like {form}", field="board", value=text)
    try:
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        square = float(parts[2])
    except ValueError:
        raise FluoInputError("board size must be COLSxROWS integers and a square size in mm",
                             field="board", value=text) from None
    min_n = 2 if kind == "chessboard" else 3
    if cols < min_n or rows < min_n:
        raise FluoInputError(f"board needs at least {min_n}x{min_n}", field="board", value=text)
    if not (np.isfinite(square) and square > 0):
        raise FluoInputError("square size must be positive [mm]", field="board", value=text)
    if kind == "chessboard":
        return Board("chessboard", cols, rows, square)
    try:
        marker = float(parts[3])
    except ValueError:
        raise FluoInputError("marker size must be a number [mm]", field="board",
                             value=text) from None
    if not (0 < marker < square):
        raise FluoInputError("marker size must be positive and smaller than the square",
                             field="board", value=text)
    dname = parts[4].upper()
    if not dname.startswith("DICT_") or not hasattr(cv2.aruco, dname):
        raise FluoInputError("unknown ArUco dictionary (e.g. DICT_5X5_100)", field="board",
                             value=parts[4])
    return Board("charuco", cols, rows, square, marker, dname)
