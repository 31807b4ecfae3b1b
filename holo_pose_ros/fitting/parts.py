"""Fit by parts: a search around the kinematic fit for the wrong basins that the starts of the whole tree do not
leave. Knows nothing of images or networks: the same evidence as Fitter.fit in, a FitResult out.

Why: a long chain fitted as a whole falls into local minima. From the exact 2D of random Baxter views seen whole,
the lifter's two best hypotheses as starts, the plain fit recovers 23 % within 5 mm; its failures are roll joints
whose range is nearly a full turn stuck at one limit while the truth lies past the other, a roll half a turn off
with the next pitch mirrored (the elbow and wrist flips), a pitch in the wrong valley, and one arm right in one
start and the other in another.

The search, after the plain fit from the given starts, is a **chain sweep**: for each chain (the subtrees hanging
from the base: Baxter's head and arms; a single arm is one chain), from the best fit, its revolute joints two at a
time from the base outwards, each pair over a grid of `parts_grid_steps` values per joint within the limits for
every member of a beam, ranked by the cost of the points that the joints so far fix, the best `parts_beam` refined
by a short fit on those points (`parts_refine_iterations`; on a Fitter restricted to them, which gives the whole
robot's result with the other points weighing 0 for a quarter less time); then one fit of the whole tree from every
chain's beam and from their combination (each chain's best under one base pose). With it Baxter's exact-2D views are
recovered in 100 % (test/test_fitting_parts.py). Measured on detected 2D and not kept (config/parts_sweep.yaml): the
base pose fitted first to the points that no joint moves, and rounds of one-joint escapes (roll joints half and whole
turns away, flips, pitch steps) from the best fit; neither changed the validation AUC beyond noise, at 5 to 20 ms more.
The lowest cost wins, and the search never returns a higher cost than the plain fit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from holo_pose_ros.fitting.kinematic_tree import KinematicTree
from holo_pose_ros.fitting.silhouette import Silhouette
from holo_pose_ros.fitting.solver import FitResult, Fitter


@dataclass(frozen=True)
class Chains:
    """How a robot's estimated joints and fit points split into chains, the subtrees hanging from the base (Baxter:
    the head and the two arms; a single arm: one)."""

    joint_chain: np.ndarray    # (J,) chain index of each joint, 0..C-1 (-1: a joint that moves no body)
    point_chain: np.ndarray    # (M,) chain index of each fit point; -1 on links that no estimated joint moves
    moves: np.ndarray          # (M, J) bool: which joints move each fit point
    n_chains: int


def chains_of(tree: KinematicTree) -> Chains:
    """The chains of `tree`: every q-driven body is assigned the body below the base that it hangs from."""
    top = np.zeros(tree.n_bodies, int) - 1
    for b in range(1, tree.n_bodies):          # bodies are numbered breadth-first: parents come first
        top[b] = b if tree.parent[b] == 0 else top[tree.parent[b]]
    roots = sorted(set(top[1:].tolist()))
    index = {r: i for i, r in enumerate(roots)}
    joint_chain = np.full(tree.n_joints, -1)
    for b in range(1, tree.n_bodies):
        if tree.gain[b] != 0.0:
            joint_chain[tree.source[b]] = index[top[b]]
    point_chain = np.array([index[top[b]] if b > 0 else -1 for b in tree.point_body], int)
    return Chains(joint_chain, point_chain, tree.point_joints, len(roots))


@dataclass(frozen=True)
class SweepStep:
    """One step of a chain's sweep: the joints it sweeps and the fit points it sees, fixed per robot."""

    pair: np.ndarray        # (1 or 2,) indices of the joints swept together
    points: np.ndarray      # (M',) fit points the step's fits work on: those the joints so far fix (the chain's and
                            # the base's) and the depth prior's
    fixed: np.ndarray       # (M',) bool: which of them the joints so far fix (the others weigh 0)
    moved: np.ndarray       # (M',) bool: which of them the pair moves
    screen: Fitter          # the short refining fit, restricted to `points`


class PartsFitter:
    """Fitter.fit plus the search of this module; build once per robot (wraps a Fitter), call fit() per frame."""

    def __init__(self, fitter: Fitter):
        self.fitter = fitter
        # the sweep's beam is refined by short fits on the points seen so far
        self.screen = Fitter(fitter.robot, {**fitter.config, "iterations": fitter.config["parts_refine_iterations"]})
        self.chains = chains_of(fitter.tree)
        self.revolute = np.array([t != "prismatic" for t in fitter.robot.joint_types])
        self.sweeps = [self.sweep_steps(c) for c in range(self.chains.n_chains)]

    def sweep_steps(self, chain: int) -> list[SweepStep]:
        """The steps of `chain`'s sweep: its revolute joints two at a time from the base outwards, each step's fits
        restricted to the points that the joints so far fix (its fits weigh the others 0, so on the whole robot
        they would cost the same for the work of every point)."""
        joints = np.flatnonzero((self.chains.joint_chain == chain) & self.revolute)
        in_chain = np.isin(self.chains.point_chain, (chain, -1))            # its points and the base's
        other = np.flatnonzero(~np.isin(np.arange(self.fitter.tree.n_joints), joints))
        steps = []
        for k in range(0, len(joints), 2):
            pair = joints[k:k + 2]
            fixed = in_chain & ~self.chains.moves[:, np.concatenate([joints[k + 2:], other])].any(axis=1)
            points = np.union1d(np.flatnonzero(fixed), self.fitter.depth_points)
            steps.append(SweepStep(pair, points, fixed[points], self.chains.moves[points][:, pair].any(axis=1),
                                   self.screen.restricted_to(points)))
        return steps

    def point_costs(self, uv: np.ndarray, weights: np.ndarray, K: np.ndarray, q: np.ndarray,
                    T_cam_base: np.ndarray, scale_px: float | None = None, fitter: Fitter | None = None) -> np.ndarray:
        """(S, M) each fit point's weighted robust reprojection cost (px^2) at poses q (S, J), T (S, 4, 4), the
        robust loss at `scale_px` (default: the fit's robust_scale_px); the points of `fitter` (default: the whole
        robot's; a sweep step's restricted one)."""
        T = np.asarray(T_cam_base, float).reshape(-1, 4, 4)
        rho, _ = (fitter or self.fitter).point_costs(uv, K, np.asarray(q, float).reshape(len(T), -1), T[:, :3, :3],
                                                     T[:, :3, 3], scale_px)
        return rho * np.asarray(weights, float)

    def combine(self, uv: np.ndarray, weights: np.ndarray, K: np.ndarray, q: np.ndarray, T_cam_base: np.ndarray,
                q_best: np.ndarray) -> np.ndarray:
        """(J,) joints taking, chain by chain, the candidate (rows of q (S, J)) whose chain points cost least under
        the one base pose T_cam_base (4, 4); joints of no chain keep q_best's values."""
        costs = self.point_costs(uv, weights, K, q, np.repeat(np.asarray(T_cam_base)[None], len(q), 0))
        out = np.array(q_best, float)
        for c in range(self.chains.n_chains):
            best = int(np.argmin(costs[:, self.chains.point_chain == c].sum(axis=1)))
            out[self.chains.joint_chain == c] = q[best, self.chains.joint_chain == c]
        return out

    def sweep_chain(self, uv: np.ndarray, w: np.ndarray, K: np.ndarray, q: np.ndarray, T_cam_base: np.ndarray,
                    chain: int, depth_prior_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A beam search down one chain from joints q (J,) and base pose T_cam_base (4, 4): its revolute joints two
        at a time from the base outwards, each pair over a grid of `parts_grid_steps` values per joint within its
        limits for every beam member, ranked by the robust cost (scale `parts_grid_scale_px`) of the points that the
        joints so far fix (and the base's), the best `parts_beam` refined by a short fit on those points. Returns
        the final beam (q (B, J), T (B, 4, 4))."""
        cfg, fitter = self.fitter.config, self.fitter
        beam_q, beam_T = q[None], T_cam_base[None]
        steps, width = int(cfg["parts_grid_steps"]), int(cfg["parts_beam"])
        for step in self.sweeps[chain]:
            seen = np.where(step.fixed, w[step.points], 0.0)                 # fixed by the joints so far
            if np.count_nonzero(seen[step.moved]) == 0:
                continue                                   # nothing these joints move is seen: keep the beam
            pair = step.pair
            grids = np.meshgrid(*[np.linspace(fitter.lower[j], fitter.upper[j], steps) for j in pair], indexing="ij")
            values = np.stack([g.ravel() for g in grids], axis=1)                  # (G, len(pair))
            cand_q = np.repeat(beam_q, len(values), 0)
            cand_q[:, pair] = np.tile(values, (len(beam_q), 1))
            cand_T = np.repeat(beam_T, len(values), 0)
            uv_seen = uv[step.points]
            costs = self.point_costs(uv_seen, seen, K, cand_q, cand_T, cfg["parts_grid_scale_px"],
                                     step.screen).sum(axis=1)
            order = np.argsort(costs, kind="stable")[:width]
            refined = step.screen.fit(uv_seen, seen, K, cand_q[order], cand_T[order], depth_prior_m=depth_prior_m)
            beam_q, beam_T = refined.q_starts, refined.T_starts
        return beam_q, beam_T

    def fit(self, uv: np.ndarray, weights: np.ndarray, K: np.ndarray, q0: np.ndarray, T0: np.ndarray,
            known_joints: np.ndarray | None = None, depth_prior_m: float | None = None,
            silhouette: Silhouette | None = None) -> FitResult:
        """As Fitter.fit, with the search (the module docstring); with known_joints only the pose is unknown and
        this is Fitter.fit. `iterations` counts the LM iterations of every fit run."""
        fitter, cfg = self.fitter, self.fitter.config
        kwargs = dict(depth_prior_m=depth_prior_m, silhouette=silhouette)
        if known_joints is not None:
            return fitter.fit(uv, weights, K, q0, T0, known_joints, **kwargs)
        uv, w = fitter.observations(uv, weights)
        best = fitter.fit(uv, w, K, q0, T0, **kwargs)
        if not np.isfinite(best.cost) or int(cfg["parts_grid_steps"]) <= 0:
            return best
        swept = [self.sweep_chain(uv, w, K, best.q, best.T_cam_base, c, depth_prior_m)
                 for c in range(self.chains.n_chains)]
        sweep_q = np.concatenate([q for q, _ in swept])
        combined = self.combine(uv, w, K, sweep_q, best.T_cam_base, best.q)
        found = fitter.fit(uv, w, K, np.concatenate([combined[None], sweep_q]),
                           np.concatenate([best.T_cam_base[None]] + [T for _, T in swept]), **kwargs)
        iterations = best.iterations + found.iterations
        if found.cost < best.cost:
            return replace(found, iterations=iterations, start_index=-1)
        return replace(best, iterations=iterations)
