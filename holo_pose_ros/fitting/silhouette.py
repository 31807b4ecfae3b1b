"""Silhouette evidence for the fit: a robot-foreground mask in frame pixels becomes a signed distance field of its
outline (bilinear samples with their gradient) and a budget of outline points with normals; residuals of projected
surface points against it, with Jacobians wrt (dq, dphi, dt) from the projection's (fitting/residuals.py). The
outline fixes the robot's apparent size, hence its depth, whatever renderer or camera made the image. Pixels (u, v),
(0, 0) the centre of the top-left pixel; the mask is the only input, no image or network.

Signed distance d = D_out - D_in, D_out the distance to the nearest foreground pixel centre (0 on the foreground),
D_in the distance to the nearest background pixel centre (0 on the background): d < 0 inside, > 0 outside, 0 on the
outline halfway between foreground and background centres. Residuals, all in pixels:
  pull-in:  every projected surface point lies inside the mask: max(d(p), 0) (the weights select d > 0);
  contour:  surface points on the contour generator (normal across the viewing ray) lie on the outline: d(p), for
            points near the outline only (an interior contour, seen in front of another link, is no evidence);
  chamfer:  every outline point b_j has a projected surface point on it: n_j . (p_nn(j) - b_j), p_nn(j) the nearest
            projected surface point, n_j the outline's normal (pull-out from afar, which pull-in cannot give).
"""

from __future__ import annotations

import cv2
import numpy as np

NORMAL_STEP_PX = 2.0  # half the stencil of the outline normals' central differences, pixels


class Silhouette:
    """A foreground mask as fit evidence. `distance` (h, w) px: the signed distance (module docstring) on a window,
    the foreground's bounding box grown by margin_px and clipped to the image, exact Euclidean; `origin` (2,) the
    window's top-left pixel (u, v); `boundary` (Nb, 2) px: midpoints between 4-adjacent foreground and background
    pixels (the outline; none along the image border, where the robot may be cut off), at most boundary_budget, a
    seeded random subset; `normals` (Nb, 2) their outward unit normals."""

    def __init__(self, mask: np.ndarray, boundary_budget: int = 200, margin_px: int = 16, seed: int = 0):
        """mask (H, W) bool (or 0/1) in frame pixels; H, W >= 2 and at least one foreground pixel."""
        mask = np.asarray(mask).astype(bool, copy=False)
        if mask.ndim != 2 or min(mask.shape) < 2:
            raise ValueError(f"expected a (H, W) mask with H, W >= 2, got shape {mask.shape}")
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if len(rows) == 0:
            raise ValueError("the silhouette mask has no foreground pixel")
        H, W = mask.shape
        m = max(int(margin_px), 1)
        v0, v1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, H)
        u0, u1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, W)
        window = mask[v0:v1, u0:u1]
        self.origin = np.array([u0, v0], float)
        self.distance = signed_distance(window)
        self._image_hi = np.array([W - 1.0, H - 1.0]) - self.origin         # the image's far corner, window pixels
        self._window_hi = np.array([window.shape[1] - 1.0, window.shape[0] - 1.0])
        boundary = outline_points(window, boundary_budget, seed)
        self.boundary = boundary + self.origin
        self.normals = self._normals(boundary)

    def _normals(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) outward unit normals at window positions points (N, 2): the signed distance's central differences
        NORMAL_STEP_PX either side (wide enough to see past the pixel staircase), clamped to the window."""
        step = np.array([[NORMAL_STEP_PX, 0.0], [0.0, NORMAL_STEP_PX]])
        ahead = bilinear(self.distance, np.clip(points[:, None] + step, 0.0, self._window_hi))[0]
        behind = bilinear(self.distance, np.clip(points[:, None] - step, 0.0, self._window_hi))[0]
        grad = ahead - behind
        return grad / np.maximum(np.sqrt(np.sum(grad * grad, axis=-1, keepdims=True)), 1e-12)

    def sample(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (...) px and its gradient (..., 2) (d/du, d/dv) at pixel positions uv (..., 2): bilinear
        inside the window (exact at pixel centres); beyond it but inside the image, the distance to the window plus
        the value at the window's nearest point (an upper bound that keeps pointing back); beyond the image, where
        there is no evidence, the value at the image's nearest point."""
        x = np.asarray(uv, float) - self.origin
        xi = np.clip(x, -self.origin, self._image_hi)                      # into the image
        xc = np.clip(xi, 0.0, self._window_hi)                              # into the window
        value, grad = bilinear(self.distance, xc)
        clamped = x != xc
        if clamped.any():
            outside = xi - xc
            gap = np.sqrt(np.sum(outside * outside, axis=-1))
            grad = np.where(clamped, 0.0, grad) + outside / np.maximum(gap, 1e-12)[..., None]
            value = value + gap
        return value, grad


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """(h, w) float64 px: distance to the nearest foreground pixel centre minus distance to the nearest background
    pixel centre, for mask (h, w) bool with some foreground (exact Euclidean, cv2.distanceTransform); 0 everywhere
    when there is no background (no outline, no evidence)."""
    if mask.all():
        return np.zeros(mask.shape)
    outside = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    inside = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return outside.astype(np.float64) - inside


def bilinear(image: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples (...) of image (h, w) (h, w >= 2) at positions x (..., 2) (u, v) within [0, w-1] x [0, h-1],
    pixel centres at integers, and their gradient (..., 2) (d/du, d/dv; one-sided at pixel centres)."""
    h, w = image.shape
    corner = np.minimum(np.floor(x), (w - 2.0, h - 2.0))
    f = x - corner
    fu, fv = f[..., 0], f[..., 1]
    flat = (corner[..., 1] * w + corner[..., 0]).astype(np.intp)
    flat_image = image.ravel()
    d00, d01, d10, d11 = flat_image[flat], flat_image[flat + 1], flat_image[flat + w], flat_image[flat + w + 1]
    top, bottom = d00 + fu * (d01 - d00), d10 + fu * (d11 - d10)
    grad = np.stack(((1.0 - fv) * (d01 - d00) + fv * (d11 - d10), bottom - top), axis=-1)
    return top + fv * (bottom - top), grad


def outline_points(mask: np.ndarray, budget: int, seed: int = 0) -> np.ndarray:
    """(N, 2) px midpoints between 4-adjacent pixels of mask (h, w) bool that differ (u, v in the mask's own
    pixels), at most budget of them: a seeded random subset, horizontal neighbours' first, each in raster order."""
    w = mask.shape[1]
    across = np.flatnonzero(mask[:, 1:] != mask[:, :-1])                  # between (v, u) and (v, u + 1)
    down = np.flatnonzero(mask[1:, :] != mask[:-1, :])                    # between (v, u) and (v + 1, u)
    n = len(across) + len(down)
    keep = np.arange(n)
    if n > budget:
        keep = np.sort(np.random.default_rng(seed).choice(n, int(budget), replace=False))
    a, d = across[keep[keep < len(across)]], down[keep[keep >= len(across)] - len(across)]
    v_a, u_a = np.divmod(a, w - 1)
    v_d, u_d = np.divmod(d, w)
    return np.column_stack([np.concatenate([u_a + 0.5, u_d]), np.concatenate([v_a, v_d + 0.5])]).astype(float)


def signed_distance_residuals(uv: np.ndarray, duv: np.ndarray | None, silhouette: Silhouette
                              ) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed distances (S, N, 1) px of projected surface points uv (S, N, 2) to the mask's outline and their
    Jacobian (S, N, 1, P) = grad d . duv from the projection's Jacobian duv (S, N, 2, P) (None: no Jacobian); the
    pull-in and contour terms weigh these."""
    d, grad = silhouette.sample(uv)
    if duv is None:
        return d[..., None], None
    return d[..., None], (grad[..., 0, None] * duv[..., 0, :] + grad[..., 1, None] * duv[..., 1, :])[..., None, :]


def contour_weights(normals_cam: np.ndarray, X_cam: np.ndarray, max_cosine: float) -> np.ndarray:
    """(S, N) weights in [0, 1] of surface points X_cam (S, N, 3) (camera frame, metres) with unit normals
    normals_cam (S, N, 3) as contour-generator points: 1 - (c / max_cosine)^2 for c = |cos(normal, viewing ray)| below
    max_cosine, else 0 (smooth, so that the cost changes little as points enter or leave)."""
    c = np.abs(np.sum(normals_cam * X_cam, axis=-1)) / np.maximum(np.sqrt(np.sum(X_cam * X_cam, axis=-1)), 1e-12)
    return np.maximum(1.0 - (c / max_cosine) ** 2, 0.0)


def nearest_points(uv: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(S, T) index of the point of uv (S, N, 2) nearest each of targets (T, 2) (pixels), per start: one matmul
    of |p|^2 - 2 b.p (the |b|^2 term does not change the argmin)."""
    lifted = np.concatenate([-2.0 * uv, np.sum(uv * uv, axis=-1, keepdims=True)], axis=-1)      # (S, N, 3)
    score = np.column_stack([targets, np.ones(len(targets))]) @ np.swapaxes(lifted, 1, 2)        # (S, T, N)
    return np.argmin(score, axis=-1)


def chamfer_residuals(uv: np.ndarray, duv: np.ndarray | None, boundary: np.ndarray, normals: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals (S, Nb, 1) px n_j . (p_nn(j) - b_j) of the outline points b (Nb, 2) px with outward normals n
    (Nb, 2), p_nn(j) the projected surface point (of uv (S, N, 2)) nearest b_j, and their Jacobian (S, Nb, 1, P):
    n_j . the rows of duv (S, N, 2, P) of those points (None: no Jacobian). Point to line, so that the gaps between
    surface points along the outline cost nothing; the match is held fixed in the derivative (as in ICP)."""
    start = np.arange(len(uv))[:, None]
    nearest = nearest_points(uv, boundary)
    r = np.sum((uv[start, nearest] - boundary) * normals, axis=-1, keepdims=True)
    if duv is None:
        return r, None
    rows = duv[start, nearest]                                                                 # (S, Nb, 2, P)
    return r, (normals[:, 0, None] * rows[..., 0, :] + normals[:, 1, None] * rows[..., 1, :])[..., None, :]
