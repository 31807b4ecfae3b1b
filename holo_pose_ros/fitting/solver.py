"""Fitter: batched Levenberg-Marquardt fit of a robot's joints q and base pose T_cam<-base to 2D fit keypoints
(pixels + confidences), from several starts solved together; the lowest final cost wins. Knows nothing of images
or networks: points, weights, K and starts in, a FitResult out. Defaults in config/fitting.yaml.

Objective per start: F = sum_i w_i rho(|r_i|^2) + W * prior_weight * sum_j ((q_j - q0_j) / sigma_j)^2, with r_i the
reprojection residual of fit point i (px), w_i its weight, W = sum_i w_i and rho the robust loss; with a depth prior
z0 also + W * depth_prior_weight * ((z - z0) / depth_prior_sigma_m)^2, z the camera depth of the root keypoint or the
mean of all fit points (depth_prior_on; 2D points fix the depth only through the robot's apparent size, which
biased 2D detections get wrong). With a silhouette (a foreground mask, fitting/silhouette.py) and the robot's surface
points (meshes at construction) also + sum_i [silhouette_weight rho_s(d_i^2) where d_i > 0 (pull-in) + contour_weight
c_i rho_s(max(d_i, -contour_gate_px)^2) (contour)] + w_k sum_j rho_s(e_j^2) (chamfer), d_i the signed distance of
surface point i to the mask's outline, c_i its contour weight, e_j the chamfer residual of outline point j, rho_s the
robust loss at silhouette_robust_scale_px (the priors keep W, the keypoints' weight). The chamfer's weight w_k starts
at chamfer_weight and halves each iteration down to chamfer_weight_final: strong, it pulls a robot seen too small or
beside the mask out onto it, where pull-in alone would shrink it into the mask; weak, it no longer biases the result
outward (the nearest surface point lies a little inside the outline). Reported costs are the data terms per unit
weight (px^2; the silhouette's weight counts every residual, the chamfer's at its final weight), without the priors.
Pose increments: see fitting/residuals.py.

Coarse to fine over the tree: the first iterations see only the points at most d q-driven joints from the base
(d = 0, step, 2 step, ...; one iteration each), then all points. Fitting the base and the proximal joints before
the distal ones keeps the distal joints from absorbing their errors: from 30-degree starts Baxter is recovered in
100 % of views instead of about 82 %.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from holo_pose_ros.fitting import compiled
from holo_pose_ros.fitting.kinematic_tree import KinematicTree
from holo_pose_ros.fitting.residuals import (
    ROBUST_LOSSES,
    project,
    reprojection_residuals_and_jacobian,
    robust_weights,
    transform_points,
)
from holo_pose_ros.fitting.silhouette import (
    Silhouette,
    chamfer_residuals,
    contour_weights,
    signed_distance_residuals,
)
from holo_pose_ros.fitting.surface import TriangleMesh, sample_surface_points
from holo_pose_ros.geometry.alignment import rotation_log
from holo_pose_ros.resources import config_with_overrides
from holo_pose_ros.robots.kinematics import RobotModel


@dataclass
class FitResult:
    """The winning start's fit. Costs are robust data costs per unit weight (px^2; keypoints, plus the silhouette
    terms when fitted to one), inf when the fit was not run (fewer than min_points usable points, no silhouette)."""

    q: np.ndarray             # (J,) joints, radians / metres, YAML order, within the URDF limits
    T_cam_base: np.ndarray    # (4, 4) robot base pose in the camera frame (OpenCV), metres
    cost: float               # the winner's final robust cost per unit weight, px^2
    rms_px: float             # the winner's confidence-weighted RMS reprojection error, px (inf: no usable point)
    start_index: int          # which start won (-1: a start that the search by parts made, fitting/parts.py)
    costs: np.ndarray         # (S,) final cost of every start, px^2
    iterations: int           # LM iterations run (chain-growing stages included)
    n_points: int             # usable points (weight >= min_confidence)
    silhouette_cost: float | None = None   # the winner's silhouette terms per unit of their weight, px^2 (None: no
                                           # silhouette)
    q_starts: np.ndarray | None = None          # (S, J) every start's final joints (the starts, when not run)
    T_starts: np.ndarray | None = None          # (S, 4, 4) every start's final T_cam<-base


@dataclass(frozen=True)
class BasePrior:
    """A pull of the base pose towards T_cam_base, e.g. a static camera's running estimate: what earlier frames say
    about a pose that does not change. Gaussian near it (sigmas per axis: metres of translation, radians of
    rotation), Cauchy beyond config base_prior_robust_sigmas, so that a pose far from it is hardly pulled."""

    T_cam_base: np.ndarray    # (4, 4) T_cam<-base
    sigma_m: float
    sigma_rad: float

    def __post_init__(self):
        T = np.asarray(self.T_cam_base, float)
        if T.shape != (4, 4) or not np.isfinite(T).all() or not (self.sigma_m > 0 and self.sigma_rad > 0):
            raise ValueError("BasePrior needs a finite 4 x 4 T_cam_base and positive sigmas")


def load_fitting_config(config: dict | str | Path | None = None) -> dict:
    """config/fitting.yaml's defaults, overridden by `config` (a dict, or the path of a YAML file of the same
    keys); unknown keys and unknown losses are errors."""
    cfg = config_with_overrides("fitting.yaml", config, "fitting parameters")
    if cfg["robust_loss"] not in ROBUST_LOSSES:
        raise ValueError(f"robust_loss '{cfg['robust_loss']}' is not one of {', '.join(ROBUST_LOSSES)}")
    return cfg


def normal_equations(r: np.ndarray, jac: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """IRLS Gauss-Newton normal matrix H = sum_i omega_i J_i^T J_i (S, P, P) and gradient g = sum_i omega_i J_i^T r_i
    (S, P) from residuals r (S, M, d), their Jacobian (S, M, d, P) and per-point weights omega (S, M)."""
    S, M, d, n = jac.shape
    J2 = jac.reshape(S, d * M, n)
    JwT = np.swapaxes((jac * omega[..., None, None]).reshape(S, d * M, n), 1, 2)   # (S, P, dM)
    return JwT @ J2, (JwT @ r.reshape(S, d * M, 1))[..., 0]


def _project_rotation(R: np.ndarray) -> np.ndarray:
    """(S, 3, 3) nearest rotations (SVD) of nearly-orthonormal matrices, so starts need not be exact."""
    U, _, Vt = np.linalg.svd(R)
    D = np.ones(R.shape[:-1])
    D[:, -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[:, None, :]) @ Vt


@dataclass
class _State:
    """Every start's parameters (q (S, J), R (S, 3, 3), t (S, 3)) and the keypoints' terms there: the IRLS normal
    equations H (S, P, P), g (S, P) at the point weights it was linearized with (`weights`, (M,)), squared residual
    norms sq (px^2), robust costs rho and IRLS weights drho (S, M); the mean camera depth z (S,) of the depth
    prior's points, metres, and its Jacobian jz (S, P); with a silhouette the
    weighted robust cost (S,) px^2 and normal equations (S, P, P), (S, P) of its pull-in and contour terms (sil_F,
    sil_H, sil_g) and of its chamfer term at unit weight (ch_F, ch_H, ch_g), else None."""

    q: np.ndarray
    R: np.ndarray
    t: np.ndarray
    weights: np.ndarray
    H: np.ndarray
    g: np.ndarray
    sq: np.ndarray
    rho: np.ndarray
    drho: np.ndarray
    z: np.ndarray
    jz: np.ndarray
    sil_F: np.ndarray | None = None
    sil_H: np.ndarray | None = None
    sil_g: np.ndarray | None = None
    ch_F: np.ndarray | None = None
    ch_H: np.ndarray | None = None
    ch_g: np.ndarray | None = None

    def where(self, take: np.ndarray, other: "_State") -> "_State":
        """Per start: `other`'s values where take (S,) is True, else this state's."""
        if take.all():
            return other
        if not take.any():
            return self
        pick = lambda a, b: np.where(take.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)  # noqa: E731
        return _State(*(a if a is None or f.name == "weights" else pick(a, b)
                        for f, a, b in ((f, getattr(self, f.name), getattr(other, f.name)) for f in fields(self))))


class Fitter:
    """Fits one robot's joints and base pose to 2D fit keypoints (and optionally a silhouette); build once, call fit()
    per frame."""

    compiled_loop = True   # fits without a silhouette or a base prior run compiled.lm_fit; False: the numpy loop
                           # of fit() (the reference, which the silhouette and base prior always take)

    def __init__(self, robot: RobotModel, config: dict | str | Path | None = None,
                 meshes: Mapping[str, TriangleMesh] | None = None):
        """`robot` gives the kinematics and joint limits; `config` overrides config/fitting.yaml. `meshes` (URDF link
        name -> vertices (V, 3) m, unit vertex normals (V, 3) and faces (F, 3) in the link frame, e.g. data/meshes.py's
        load_link_meshes) give the surface points (config surface_points of them) that a silhouette is fitted with."""
        self.robot = robot
        self.config = load_fitting_config(config)
        self.tree = KinematicTree.from_robot(robot)
        self.surface_tree, self.surface_normals = None, None
        if meshes is not None:
            surface = sample_surface_points(meshes, int(self.config["surface_points"]))
            self.surface_tree = self.tree.with_link_points({name: p for name, (p, _) in surface.items()})
            # (N, 3) unit normals in the points' body frames
            self.surface_normals = np.concatenate([n @ self.tree.link_frames[name][1][:3, :3].T
                                                   for name, (_, n) in surface.items()])
        self.lower = robot.lower.detach().cpu().double().numpy()
        self.upper = robot.upper.detach().cpu().double().numpy()
        sigma = np.array([self.config["prior_sigma_m"] if t == "prismatic" else self.config["prior_sigma_rad"]
                          for t in robot.joint_types], float)
        self._prior_precision = float(self.config["prior_weight"]) / sigma ** 2    # (J,) px^2 per unit weight
        on = self.config["depth_prior_on"]
        if on not in ("root", "centroid"):
            raise ValueError(f"depth_prior_on must be root or centroid, got '{on}'")
        # fit points whose mean depth the depth prior holds: the root keypoint (a DREAM keypoint, so fit point
        # root_index) or all of them
        self.depth_points = np.array([robot.root_index]) if on == "root" else np.arange(self.tree.n_points)

    def restricted_to(self, points: np.ndarray) -> "Fitter":
        """This Fitter over the fit points at indices `points` only (M' of them: uv and weights then have M' rows),
        which must hold the depth prior's points. A fit whose other points weigh 0 gives the same result on it, with
        the work of M' points (the search by parts fits subsets of the points many times a frame). No silhouette."""
        idx = np.asarray(points, int).reshape(-1)
        where = {int(m): i for i, m in enumerate(idx)}
        if any(int(m) not in where for m in self.depth_points):
            raise ValueError("a restricted Fitter must keep the depth prior's points")
        restricted = copy.copy(self)
        restricted.tree = self.tree.restricted_to(idx)
        restricted.depth_points = np.array([where[int(m)] for m in self.depth_points])
        restricted.surface_tree, restricted.surface_normals = None, None
        return restricted

    # -- inputs ---------------------------------------------------------------------------------------------
    def silhouette(self, mask: np.ndarray) -> Silhouette:
        """The fit evidence of a robot-foreground mask (H, W) bool in frame pixels, with the config's outline budget
        (silhouette_boundary_points) and window margin (silhouette_margin_px)."""
        cfg = self.config
        return Silhouette(mask, int(cfg["silhouette_boundary_points"]), int(cfg["silhouette_margin_px"]))

    def observations(self, uv: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """uv (M, 2) px and weights (M,) checked; non-finite or low-confidence points get weight 0."""
        M = self.tree.n_points
        uv = np.asarray(uv, float).reshape(-1, 2)
        w = np.asarray(weights, float).reshape(-1)
        if len(uv) != M or len(w) != M:
            raise ValueError(f"{self.robot.name}: expected {M} fit keypoints, got uv {len(uv)} and weights {len(w)}")
        bad = ~np.isfinite(uv).all(axis=1) | ~np.isfinite(w) | (w < self.config["min_confidence"])
        return np.where(bad[:, None], 0.0, uv), np.where(bad, 0.0, w)

    def _starts(self, q0: np.ndarray, T0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q (S, J) clamped to the limits, R (S, 3, 3) projected onto SO(3), t (S, 3) from the starts."""
        J = self.tree.n_joints
        q = np.clip(np.asarray(q0, float).reshape(-1, J), self.lower, self.upper)
        T = np.asarray(T0, float).reshape(-1, 4, 4)
        if len(T) != len(q):
            raise ValueError(f"got {len(q)} joint starts but {len(T)} pose starts")
        return q, _project_rotation(T[:, :3, :3]), T[:, :3, 3].copy()

    def _stage_weights(self, w: np.ndarray) -> list[np.ndarray]:
        """The chain-growing stages' point weights (M,) each: w on points at most d q-driven joints from the
        base, d = 0, step, 2 step, ...; stages with fewer than min_points usable points or nothing new are left out."""
        step = int(self.config["grow_chain_levels"])
        depth = self.tree.point_depth
        stages: list[np.ndarray] = []
        if step <= 0:
            return stages
        n_all = np.count_nonzero(w)
        for d in range(0, int(depth.max(initial=0)), step):
            wd = np.where(depth <= d, w, 0.0)
            n = np.count_nonzero(wd)
            if n >= self.config["min_points"] and n < n_all and (not stages or n > np.count_nonzero(stages[-1])):
                stages.append(wd)
        return stages

    # -- cost -----------------------------------------------------------------------------------------------
    def cost(self, uv: np.ndarray, weights: np.ndarray, K: np.ndarray, q: np.ndarray,
             T_cam_base: np.ndarray, silhouette: Silhouette | None = None) -> np.ndarray:
        """(S,) robust reprojection cost per unit weight (px^2, no prior) of given poses q (S, J), T_cam<-base
        (S, 4, 4), e.g. to compare feed-forward estimates with a fit; with a silhouette, its terms too (as fit
        weighs them); inf where no point is usable."""
        uv, w = self.observations(uv, weights)
        q = np.asarray(q, float).reshape(-1, self.tree.n_joints)
        T = np.asarray(T_cam_base, float).reshape(-1, 4, 4)
        K, R, t = np.asarray(K, float), T[:, :3, :3], T[:, :3, 3]
        F_data, _ = self._data_terms(uv, w, K, q, R, t)
        W = w.sum()
        if silhouette is not None:
            self._require_surface()
            normals = self.surface_tree.directions(self.surface_tree.body_poses(q), self.surface_normals)
            terms = self._silhouette_terms(silhouette, K, self.surface_tree.points(q), normals, None, R, t, False)
            F_data = F_data + terms[0] + self.config["chamfer_weight_final"] * terms[3]
            W += self._silhouette_weight(silhouette)
        return F_data / W if W > 0 else np.full(len(q), np.inf)

    def project(self, q: np.ndarray, T_cam_base: np.ndarray, K: np.ndarray) -> np.ndarray:
        """(M, 2) pixels where the fit keypoints lie at joints q (J,) and pose T_cam<-base (4, 4) through K."""
        T = np.asarray(T_cam_base, float)
        P = self.tree.points(np.asarray(q, float)[None])
        return project(transform_points(P, T[None, :3, :3], T[None, :3, 3]), np.asarray(K, float),
                       self.config["min_depth_m"])[0]

    def _data_terms(self, uv: np.ndarray, w: np.ndarray, K: np.ndarray, q: np.ndarray, R: np.ndarray,
                    t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sum w rho(|r|^2) (S,) and sum w |r|^2 (S,), px^2, at poses (q, R, t) without derivatives."""
        rho, s = self.point_costs(uv, K, q, R, t)
        return rho @ w, s @ w

    def point_costs(self, uv: np.ndarray, K: np.ndarray, q: np.ndarray, R: np.ndarray, t: np.ndarray,
                    scale_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Each fit point's robust cost rho(|r|^2) and squared reprojection error |r|^2 (S, M), px^2, unweighted, at
        poses (q (S, J), R (S, 3, 3), t (S, 3)); the robust loss at scale_px (default robust_scale_px). Compiled."""
        cfg = self.config
        c = np.ascontiguousarray
        return compiled.point_costs(c(q, np.float64), c(R, np.float64), c(t, np.float64), *self.tree.compiled_arrays,
                                    c(K, np.float64), c(uv, np.float64), compiled.LOSS_CODES[cfg["robust_loss"]],
                                    float(cfg["robust_scale_px"] if scale_px is None else scale_px),
                                    float(cfg["min_depth_m"]))

    def _require_surface(self) -> None:
        """An error when the Fitter was built without meshes, so has no surface points to fit a silhouette with."""
        if self.surface_tree is None:
            raise ValueError("fitting a silhouette needs the robot's surface points: build the Fitter with meshes")

    def _silhouette_weight(self, silhouette: Silhouette) -> float:
        """The silhouette terms' weight if every residual were active, (silhouette_weight + contour_weight) per surface
        point + chamfer_weight_final per outline point: the unit of their reported cost."""
        cfg = self.config
        return ((cfg["silhouette_weight"] + cfg["contour_weight"]) * self.surface_tree.n_points
                + cfg["chamfer_weight_final"] * len(silhouette.boundary))

    def _silhouette_terms(self, silhouette: Silhouette, K: np.ndarray, P: np.ndarray, normals: np.ndarray,
                          dP: np.ndarray | None, R: np.ndarray, t: np.ndarray, derivatives: bool = True
                          ) -> tuple[np.ndarray, ...]:
        """Weighted robust cost (S,) px^2 of the pull-in and contour residuals (fitting/silhouette.py) of surface
        points P (S, N, 3) with unit normals (S, N, 3) (base frame, metres) through poses (R, t) and K, and with
        derivatives their normal equations H (S, P, P), g (S, P) wrt (dq, dphi, dt) (dP (S, N, 3, J) from the tree,
        None for a pose-only fit; else None, None); then the same three for the chamfer residuals at unit weight."""
        cfg = self.config
        loss, scale, gate = cfg["robust_loss"], cfg["silhouette_robust_scale_px"], cfg["contour_gate_px"]
        X = transform_points(P, R, t)
        if derivatives:
            uv, duv = reprojection_residuals_and_jacobian(P, dP, R, t, K, np.zeros(2), cfg["min_depth_m"])
        else:
            uv, duv = project(X, K, cfg["min_depth_m"]), None
        # pull-in and contour share the signed distance d: pull-in where d > 0, contour on contour-generator points
        # with d capped at -gate inside (an interior contour costs a constant, with no pull)
        d, jac = signed_distance_residuals(uv, duv, silhouette)
        d = d[..., 0]
        contour = cfg["contour_weight"] * contour_weights(normals @ np.swapaxes(R, 1, 2), X, cfg["contour_max_cosine"])
        pull = cfg["silhouette_weight"] * (d > 0.0)
        rho, drho = robust_weights(d * d, loss, scale)
        rho_capped, _ = robust_weights(np.maximum(d, -gate) ** 2, loss, scale)
        F = np.sum(pull * rho + contour * rho_capped, axis=-1)
        r, jac_ch = chamfer_residuals(uv, duv, silhouette.boundary, silhouette.normals)
        rho_ch, drho_ch = robust_weights(r[..., 0] ** 2, loss, scale)
        if not derivatives:
            return F, None, None, rho_ch.sum(axis=-1), None, None
        return (F, *normal_equations(d[..., None], jac, drho * (pull + contour * (d > -gate))),
                rho_ch.sum(axis=-1), *normal_equations(r, jac_ch, drho_ch))

    # -- fit ------------------------------------------------------------------------------------------------
    def fit(self, uv: np.ndarray, weights: np.ndarray, K: np.ndarray, q0: np.ndarray, T0: np.ndarray,
            known_joints: np.ndarray | None = None, depth_prior_m: float | None = None,
            silhouette: Silhouette | None = None, base_prior: BasePrior | None = None) -> FitResult:
        """Fit to fit keypoints uv (M, 2) px with weights (M,) >= 0 seen through K (3, 3), from starts q0 (S, J)
        and T0 (S, 4, 4) (T_cam<-base); with known_joints (J,) q is held there and only the pose is fitted. With
        depth_prior_m, the depth of `depth_points` (config depth_prior_on: the root keypoint or all fit points) is
        pulled towards it (metres; e.g. a depth network's). With base_prior the base pose is pulled towards its
        T_cam_base (config base_prior_weight at one sigma, robust beyond base_prior_robust_sigmas; its cost also
        counts in the choice of the winning start). With a silhouette (Fitter.silhouette(mask); needs meshes at
        construction) its terms join the keypoints' at every iteration and in the choice of the winning start,
        and the fit runs even without usable keypoints."""
        cfg = self.config
        uv, w = self.observations(uv, weights)
        K = np.asarray(K, float)
        q, R, t = self._starts(q0, T0)
        S, J = q.shape
        W = float(w.sum())
        n_points = int(np.count_nonzero(w))
        pose_only = known_joints is not None
        if silhouette is not None:
            self._require_surface()
        W_sil = 0.0 if silhouette is None else self._silhouette_weight(silhouette)
        W_all = W + W_sil                                           # the unit of the reported cost
        if pose_only:
            q_known = np.asarray(known_joints, float).reshape(J)
            q = np.repeat(q_known[None], S, axis=0)
            P_known = np.repeat(self.tree.points(q_known[None]), S, axis=0)
            if silhouette is not None:
                T_bodies = self.surface_tree.body_poses(q_known[None])
                normals_known = np.repeat(self.surface_tree.directions(T_bodies, self.surface_normals), S, axis=0)
                P_surface_known = np.repeat(self.surface_tree.points(q_known[None]), S, axis=0)

        if n_points < cfg["min_points"] and silhouette is None:
            F_data, sq = self._data_terms(uv, w, K, q, R, t)
            best = int(np.argmin(F_data))
            T_starts = self._matrices(R, t)
            return FitResult(q[best].copy(), T_starts[best], float("inf"), self._rms(sq[best] / max(W, 1e-300), W),
                             best, np.full(S, np.inf), 0, n_points, None, q.copy(), T_starts)

        min_depth, loss, scale = cfg["min_depth_m"], compiled.LOSS_CODES[cfg["robust_loss"]], cfg["robust_scale_px"]
        P_fixed = np.ascontiguousarray(P_known) if pose_only else np.zeros((1, 1, 3))
        uv_c, depth_points = np.ascontiguousarray(uv), np.ascontiguousarray(self.depth_points, np.int64)

        def linearize(q: np.ndarray, R: np.ndarray, t: np.ndarray, weights: np.ndarray) -> _State:
            """The normal equations (points weighing `weights` (M,) times their IRLS weights) and robust terms at
            (q, R, t), compiled (fitting/compiled.py)."""
            terms = compiled.linearize(np.ascontiguousarray(q, np.float64), np.ascontiguousarray(R, np.float64),
                                       np.ascontiguousarray(t, np.float64), P_fixed, pose_only,
                                       *self.tree.compiled_arrays, K, uv_c, weights, loss, scale, min_depth,
                                       depth_points)
            sq, rho, drho, H, g, z, jz = terms
            sil = ()
            if silhouette is not None:
                if pose_only:
                    Ps, Ns, dPs = P_surface_known, normals_known, None
                else:
                    T_bodies = self.surface_tree.body_poses(q)
                    Ns = self.surface_tree.directions(T_bodies, self.surface_normals)
                    Ps, dPs = self.surface_tree.points_and_jacobian_at(T_bodies)
                sil = self._silhouette_terms(silhouette, K, Ps, Ns, dPs, R, t)
            return _State(q, R, t, weights, H, g, sq, rho, drho, z, jz, *sil)

        def data_cost(state: _State) -> np.ndarray:
            """(S,) the keypoints' robust cost at all weights plus the silhouette terms (the chamfer at its final
            weight), px^2."""
            if state.sil_F is None:
                return state.rho @ w
            return state.rho @ w + state.sil_F + cfg["chamfer_weight_final"] * state.ch_F

        def chamfer_weight(k: int) -> float:
            """The chamfer's weight at iteration k: chamfer_weight halved each iteration, down to the final."""
            return max(float(cfg["chamfer_weight_final"]), float(cfg["chamfer_weight"]) * 0.5 ** (k - 1))

        q_start = q.copy()
        prior = self._prior_precision * W                                      # (J,) per unit of (q - q0)^2
        nq = 0 if pose_only else J

        depth_weight = cfg["depth_prior_weight"] if not pose_only or cfg["known_joints_depth_prior_weight"] is None \
            else cfg["known_joints_depth_prior_weight"]
        depth_precision = 0.0 if depth_prior_m is None else W * float(depth_weight) / cfg["depth_prior_sigma_m"] ** 2
        depth_m = 0.0 if depth_prior_m is None else float(depth_prior_m)
        if base_prior is not None:
            R_prior = np.asarray(base_prior.T_cam_base, float)[:3, :3]
            t_prior = np.asarray(base_prior.T_cam_base, float)[:3, 3]
            base_unit = W * cfg["base_prior_weight"]                           # px^2 at one sigma
            precision_t, precision_r = base_unit / base_prior.sigma_m ** 2, base_unit / base_prior.sigma_rad ** 2
            base_scale2 = float(cfg["base_prior_robust_sigmas"]) ** 2

        def base_sigmas2(state: _State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """(S,) the squared distance to the base prior in sigmas, and its residuals: (S, 3) the rotation vector
            of R_prior^T R (rad) and (S, 3) t - t_prior (m)."""
            e_r, e_t = rotation_log(np.swapaxes(R_prior, -1, -2) @ state.R), state.t - t_prior
            return (np.sum(e_r ** 2, -1) * precision_r + np.sum(e_t ** 2, -1) * precision_t) / base_unit, e_r, e_t

        def base_cost(state: _State) -> np.ndarray | float:
            """(S,) the base prior's robust (Cauchy) cost, 0 without one, px^2: quadratic near the prior, growing only
            logarithmically beyond base_prior_robust_sigmas (a moved camera is not pulled back)."""
            if base_prior is None:
                return 0.0
            return base_unit * base_scale2 * np.log1p(base_sigmas2(state)[0] / base_scale2)

        def prior_cost(state: _State) -> np.ndarray:
            joints = 0.0 if pose_only else ((state.q - q_start) ** 2) @ prior
            return joints + (0.0 if depth_prior_m is None else depth_precision * (state.z - depth_prior_m) ** 2) \
                + base_cost(state)

        stages = [] if pose_only else self._stage_weights(w)[:int(cfg["iterations"]) // 2]  # half at least see all
        if self.compiled_loop and silhouette is None and base_prior is None:   # the loop below, compiled
            q_f, R_f, t_f, end, end_sq, begin, begin_sq, iterations = compiled.lm_fit(
                q, R, t, np.stack(stages) if stages else np.zeros((0, len(w))), w, P_fixed, pose_only,
                *self.tree.compiled_arrays, K, uv_c, loss, scale, min_depth, depth_points, prior, depth_precision,
                depth_m, self.lower, self.upper, int(cfg["iterations"]), float(cfg["damping_init"]),
                float(cfg["damping_up"]), float(cfg["damping_down"]), float(cfg["damping_min"]),
                float(cfg["damping_max"]), float(cfg["relative_tolerance"]),
                float(cfg["absolute_tolerance_px2"]) * W_all)
            back = end > begin                          # never worse than the start itself (see below)
            q_f, R_f, t_f = (np.where(back.reshape((-1,) + (1,) * (a.ndim - 1)), a, f)
                             for a, f in ((q, q_f), (R, R_f), (t, t_f)))
            costs = np.where(back, begin, end) / W_all
            best = int(np.argmin(costs))
            T_starts = self._matrices(R_f, t_f)
            return FitResult(q_f[best].copy(), T_starts[best], float(costs[best]),
                             self._rms(np.where(back, begin_sq, end_sq)[best] / max(W, 1e-300), W), best, costs,
                             int(iterations), n_points, None, q_f.copy(), T_starts)
        state = linearize(q, R, t, stages[0] if stages else w)
        start_state = state
        damping = np.full(S, float(cfg["damping_init"]))
        converged = np.zeros(S, bool)
        iterations = 0
        for iterations in range(1, int(cfg["iterations"]) + 1):
            final = iterations > len(stages)
            wk = w if final else stages[iterations - 1]
            if state.weights is not wk:                                        # a new chain-growing stage
                state = linearize(state.q, state.R, state.t, wk)
            H, g = state.H, state.g
            F = state.rho @ wk + prior_cost(state)
            if silhouette is not None:
                wc = chamfer_weight(iterations)
                H = H + state.sil_H + wc * state.ch_H
                g = g + state.sil_g + wc * state.ch_g
                F += state.sil_F + wc * state.ch_F
            if base_prior is not None:  # IRLS of the Cauchy; the rotation's Jacobian taken as the identity
                d2, e_r, e_t = base_sigmas2(state)
                down = (1.0 / (1.0 + d2 / base_scale2))[:, None]
                rot, trans = np.arange(nq, nq + 3), np.arange(nq + 3, nq + 6)
                H, g = H.copy(), g.copy()
                H[:, rot, rot] += precision_r * down
                H[:, trans, trans] += precision_t * down
                g[:, nq:nq + 3] += precision_r * down * e_r
                g[:, nq + 3:nq + 6] += precision_t * down * e_t
            # the depth and joint priors, the limits (projected Newton) and the damped step, compiled
            cand = linearize(*compiled.propose(state.q, state.R, state.t, H, g, q_start, prior, state.z, state.jz,
                                               depth_precision, depth_m, self.lower, self.upper, damping, pose_only),
                             wk)
            F_c = cand.rho @ wk + prior_cost(cand)
            if silhouette is not None:
                F_c += cand.sil_F + wc * cand.ch_F
            accept = F_c < F                                                   # False for NaN
            if final and (silhouette is None or wc == cfg["chamfer_weight_final"]):
                converged |= accept & (((F - F_c) < cfg["relative_tolerance"] * F)
                                       | (data_cost(cand) < cfg["absolute_tolerance_px2"] * W_all))
                converged |= ~accept & (damping >= cfg["damping_max"])
            state = state.where(accept, cand)
            damping = np.clip(damping * np.where(accept, cfg["damping_down"], cfg["damping_up"]),
                              cfg["damping_min"], cfg["damping_max"])
            if converged.all():
                break

        # the coarse-to-fine stages descend on subsets of the points: a start may end above where it began on all of
        # them (seen on real detections); never return worse than the start itself
        # (with a base prior, its cost counts too: the prior's pull is what it is there for)
        end, begin = data_cost(state), data_cost(start_state)
        end_base, begin_base = base_cost(state), base_cost(start_state)
        back = end + end_base > begin + begin_base
        state = state.where(back, start_state)
        costs = np.where(back, begin, end) / W_all
        best = int(np.argmin(costs + np.where(back, begin_base, end_base) / W_all))
        silhouette_cost = None if silhouette is None else float((data_cost(state) - state.rho @ w)[best] / W_sil)
        T_starts = self._matrices(state.R, state.t)
        return FitResult(state.q[best].copy(), T_starts[best], float(costs[best]),
                         self._rms(state.sq[best] @ w / max(W, 1e-300), W), best, costs, iterations, n_points,
                         silhouette_cost, state.q.copy(), T_starts)

    def prior_depth(self, q: np.ndarray, T_cam_base: np.ndarray) -> float:
        """The depth (metres) that the depth prior holds, at joints q (J,) and pose T_cam_base (4, 4): the mean
        camera depth of `depth_points` (config depth_prior_on)."""
        P = self.tree.points(np.asarray(q, float)[None])[0, self.depth_points]
        T = np.asarray(T_cam_base, float)
        return float((P @ T[2, :3] + T[2, 3]).mean())

    @staticmethod
    def _matrices(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(S, 4, 4) homogeneous transforms from R (S, 3, 3), t (S, 3)."""
        T = np.zeros((len(R), 4, 4))
        T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, t, 1.0
        return T

    @staticmethod
    def _rms(mean_sq_px2: float, W: float) -> float:
        """RMS in px from a weighted mean square; inf when nothing carried weight."""
        return float(np.sqrt(mean_sq_px2)) if W > 0 else float("inf")
