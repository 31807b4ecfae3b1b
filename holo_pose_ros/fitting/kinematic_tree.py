"""KinematicTree: a robot's URDF compiled into float64 numpy arrays for fast batched forward kinematics of the fit
keypoints and their analytic Jacobian with respect to the estimated joints. Metres, radians.

Why not RobotModel: the fit calls FK some ten times per frame on a few starts; numpy on small arrays costs a
fraction of torch / pytorch-kinematics' per-call overhead. RobotModel stays the reference (the tests compare).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from holo_pose_ros.robots.kinematics import RobotModel

_MOVING_TYPES = ("revolute", "continuous", "prismatic")


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by `angle` radians about the unit `axis` (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _joint_motion(kind: str, axis: np.ndarray, value: float) -> np.ndarray:
    """(4, 4) motion of a URDF joint at `value` (radians or metres) in its own frame; identity for fixed joints."""
    T = np.eye(4)
    if kind in ("revolute", "continuous"):
        T[:3, :3] = _rotation_about(axis, value)
    elif kind == "prismatic":
        T[:3, 3] = axis * value
    return T


@dataclass(frozen=True)
class _Edge:
    """One URDF joint seen from the base: `to` is reached from `frm`; `forward` when frm is the URDF parent."""

    joint: object
    frm: str
    to: str
    forward: bool


class KinematicTree:
    """The fit keypoints of one robot as a tree of moving bodies, in the spec's base_link frame.

    Each body b >= 1 hangs from body parent[b] through a constant transform C_b followed by one joint motion
    M_b(theta_b) about (revolute) or along (prismatic) the unit axis_b (in the frame after C_b), with
    theta_b = gain_b * q[source_b] + bias_b: URDF mimics and the re-rooting at base_link fold into gain and
    bias. Joints whose value does not depend on q (fixed, or non-estimated at spec.fixed_joints) are folded
    into the constants, so only q-driven joints cost anything at run time. Body 0 is the base.
    """

    def __init__(self, parent: np.ndarray, C: np.ndarray, axis: np.ndarray, prismatic: np.ndarray,
                 source: np.ndarray, gain: np.ndarray, bias: np.ndarray, point_body: np.ndarray,
                 point_local: np.ndarray, n_joints: int,
                 link_frames: Mapping[str, tuple[int, np.ndarray]] | None = None):
        """Arrays as built by from_robot: per body (B,) parent / (B,4,4) C / (B,3) axis / (B,) prismatic,
        source, gain, bias (entries of body 0 unused); per fit point (M,) body and (M,3) position in it (metres);
        link_frames: URDF link name -> (body, T_body<-link (4, 4)), for placing other points (with_link_points)."""
        self.link_frames = dict(link_frames or {})
        self.parent, self.C, self.axis = parent, C, axis
        self.prismatic, self.source, self.gain, self.bias = prismatic, source, gain, bias
        self.point_body, self.point_local = point_body, point_local
        self.n_joints = n_joints
        self.n_bodies = len(parent)
        self.n_points = len(point_body)
        moving = np.arange(1, self.n_bodies)
        revolute = ~prismatic[moving]
        # Local transform of a body at theta (B-1 moving bodies): C + sin(theta) C[a]x + (1 - cos(theta)) C[a]x^2
        # (revolute, Rodrigues) or C + theta * (C a) in the translation column (prismatic); pieces precomputed.
        a = axis[moving]
        K = np.zeros((len(moving), 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = a[:, 2], -a[:, 1], a[:, 0]
        K *= revolute[:, None, None]
        self._C = C[moving]
        self._CK, self._CKK, self._Ca = (np.zeros_like(self._C) for _ in range(3))
        self._CK[:, :3, :3] = self._C[:, :3, :3] @ K
        self._CKK[:, :3, :3] = self._C[:, :3, :3] @ K @ K
        self._Ca[:, :3, 3] = (self._C[:, :3, :3] @ a[:, :, None])[..., 0] * (~revolute)[:, None]
        self._theta_source, self._theta_gain, self._theta_bias = source[moving], gain[moving], bias[moving]
        # Depth levels: the FK loop runs over tree depth (Baxter's arms side by side), with plain indices where
        # a level holds one body (a chain).
        depth = np.zeros(self.n_bodies, int)
        for b in moving:
            depth[b] = depth[parent[b]] + 1
        self.point_depth = depth[point_body]                                  # (M,) q-driven joints above each point
        self._levels = []
        for d in range(1, depth.max(initial=0) + 1):
            idx = np.flatnonzero(depth == d)
            self._levels.append((int(idx[0]), int(parent[idx[0]])) if len(idx) == 1 else (idx, parent[idx]))
        # Jacobian pieces: coef[b, m] = gain_b where body b lies on point m's path to the base (its joint moves
        # the point), else 0; to_joint maps bodies to the q index driving them.
        ancestor = np.zeros((self.n_bodies, self.n_points), bool)
        for m, b in enumerate(point_body):
            while b > 0:
                ancestor[b, m] = True
                b = parent[b]
        self._skew_local = np.concatenate([np.zeros((1, 3, 3)), K])          # (B, 3, 3), zero unless revolute
        self._prismatic_axis = (axis * prismatic[:, None])[:, :, None]      # (B, 3, 1), zero unless prismatic
        self._coef = (gain[:, None] * ancestor)[:, None, :]                    # (B, 1, M)
        self._to_joint = np.zeros((self.n_bodies, n_joints))
        self._to_joint[moving, source[moving]] = 1.0
        self.point_joints = (np.abs(self._coef[:, 0, :]).T @ self._to_joint) > 0   # (M, J) bool: joints moving a point
        self._local_h = np.concatenate([point_local, np.ones((self.n_points, 1))], axis=1).T.copy()  # (4, M)
        self._point_index = np.arange(self.n_points)
        # the same tree as the compiled linearization (fitting/compiled.py) takes it: contiguous, fixed dtypes
        f64, i64 = (lambda a: np.ascontiguousarray(a, np.float64)), (lambda a: np.ascontiguousarray(a, np.int64))
        self.compiled_arrays = (i64(parent), f64(self._C), f64(self._CK), f64(self._CKK), f64(self._Ca), i64(source),
                                f64(gain), f64(bias), f64(axis), np.ascontiguousarray(prismatic, np.bool_),
                                i64(point_body), f64(point_local), int(n_joints))

    # -- construction ---------------------------------------------------------------------------------------
    @classmethod
    def from_robot(cls, robot: RobotModel) -> "KinematicTree":
        """Compile `robot`'s URDF (yourdfpy), its mimics, fixed_joints and base_link into the tree's arrays."""
        spec, urdf = robot.spec, robot.urdf
        estimated = {j.urdf: i for i, j in enumerate(spec.joints)}

        def drive(joint) -> tuple[int, float, float]:
            """(source index or -1, gain, bias) of a URDF joint's value, as RobotModel.full_configuration."""
            lead, m, o = joint.name, 1.0, 0.0
            if joint.mimic is not None:
                lead, m, o = joint.mimic.joint, float(joint.mimic.multiplier or 1.0), float(joint.mimic.offset or 0.0)
            if joint.type not in _MOVING_TYPES:
                return -1, 0.0, 0.0
            if lead in estimated:
                return estimated[lead], m, o
            return -1, 0.0, m * spec.fixed_joints.get(lead, 0.0) + o

        adjacent: dict[str, list[_Edge]] = defaultdict(list)
        for j in urdf.robot.joints:
            adjacent[j.parent].append(_Edge(j, j.parent, j.child, True))
            adjacent[j.child].append(_Edge(j, j.child, j.parent, False))

        # Breadth-first from base_link: every link gets (body, T_body<-link).
        link_body: dict[str, tuple[int, np.ndarray]] = {spec.base_link: (0, np.eye(4))}
        parent, C, axis, prismatic, source, gain, bias = [0], [np.eye(4)], [np.zeros(3)], [False], [0], [0.0], [0.0]
        queue = [spec.base_link]
        while queue:
            link = queue.pop(0)
            body, T_body_link = link_body[link]
            for e in adjacent[link]:
                if e.to in link_body:
                    continue
                j = e.joint
                origin = np.asarray(j.origin, float) if j.origin is not None else np.eye(4)
                ax = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), float)
                ax = ax / np.linalg.norm(ax)
                src, m, o = drive(j)
                sign = 1.0 if e.forward else -1.0
                # forward: T_from<-to = origin M(theta); reverse: T_from<-to = M(-theta) origin^-1
                before, after = (origin, np.eye(4)) if e.forward else (np.eye(4), np.linalg.inv(origin))
                if src < 0:
                    T = T_body_link @ before @ _joint_motion(j.type, ax, sign * o) @ after
                    link_body[e.to] = (body, T)
                else:
                    parent.append(body); C.append(T_body_link @ before); axis.append(ax)
                    prismatic.append(j.type == "prismatic"); source.append(src)
                    gain.append(sign * m); bias.append(sign * o)
                    link_body[e.to] = (len(parent) - 1, after)
                queue.append(e.to)

        points = spec.fit_keypoints
        point_body = np.array([link_body[k.link][0] for k in points], int)
        point_local = np.array([(link_body[k.link][1] @ np.array([*k.xyz, 1.0]))[:3] for k in points],
                               float).reshape(-1, 3)
        return cls(np.array(parent, int), np.array(C), np.array(axis), np.array(prismatic, bool), np.array(source, int),
                   np.array(gain, float), np.array(bias, float), point_body, point_local, robot.n_joints, link_body)

    def with_link_points(self, link_points: Mapping[str, np.ndarray]) -> "KinematicTree":
        """The same bodies carrying other points instead of the fit keypoints (e.g. the silhouette's surface points):
        link name -> (N_l, 3) positions in that URDF link's frame, metres, concatenated in the mapping's order."""
        unknown = [name for name in link_points if name not in self.link_frames]
        if unknown:
            raise ValueError(f"links {unknown} are not in the kinematic tree")
        body, local = [], []
        for name, points in link_points.items():
            b, T = self.link_frames[name]
            points = np.asarray(points, float).reshape(-1, 3)
            body.append(np.full(len(points), b, int))
            local.append(points @ T[:3, :3].T + T[:3, 3])
        return KinematicTree(self.parent, self.C, self.axis, self.prismatic, self.source, self.gain, self.bias,
                             np.concatenate(body), np.concatenate(local), self.n_joints, self.link_frames)

    def restricted_to(self, points: np.ndarray) -> "KinematicTree":
        """The tree carrying only the fit points at indices `points` (in that order), and only the bodies on their
        paths to the base: a fit that weighs the other points 0 costs the same on it for a fraction of the work (the
        search by parts' sweep). Links on the bodies left out are left out of link_frames."""
        idx = np.asarray(points, int).reshape(-1)
        keep = np.zeros(self.n_bodies, bool)
        keep[0] = True
        for b in set(self.point_body[idx].tolist()):
            while not keep[b]:
                keep[b], b = True, self.parent[b]
        bodies = np.flatnonzero(keep)                 # breadth-first order kept: parents still come first
        new = np.full(self.n_bodies, -1)
        new[bodies] = np.arange(len(bodies))
        parent = new[self.parent[bodies]]
        parent[0] = 0
        frames = {name: (int(new[b]), T) for name, (b, T) in self.link_frames.items() if keep[b]}
        return KinematicTree(parent, self.C[bodies], self.axis[bodies], self.prismatic[bodies], self.source[bodies],
                             self.gain[bodies], self.bias[bodies], new[self.point_body[idx]], self.point_local[idx],
                             self.n_joints, frames)

    # -- kinematics -----------------------------------------------------------------------------------------
    def body_poses(self, q: np.ndarray) -> np.ndarray:
        """(S, B, 4, 4) poses T_base<-body of every body (joint frames after their motion) for joints q (S, J)."""
        q = np.asarray(q, float).reshape(-1, self.n_joints)
        theta = q[:, self._theta_source] * self._theta_gain + self._theta_bias        # (S, B-1)
        s = np.sin(theta)[..., None, None]
        c = 1.0 - np.cos(theta)[..., None, None]
        L = self._C + s * self._CK + c * self._CKK + theta[..., None, None] * self._Ca
        T = np.empty((len(q), self.n_bodies, 4, 4))
        T[:, 0] = np.eye(4)
        for idx, par in self._levels:
            T[:, idx] = T[:, par] @ L[:, idx - 1]
        return T

    def points(self, q: np.ndarray) -> np.ndarray:
        """(S, M, 3) fit keypoints in the base frame, metres, for joints q (S, J) (radians / metres)."""
        return self._apply(self.body_poses(q))

    def _apply(self, T: np.ndarray) -> np.ndarray:
        """Fit points (S, M, 3) from body poses (S, B, 4, 4): every body maps every point (one batched matmul, far
        cheaper than gathering a 4x4 per point), then each point keeps its own body's result."""
        X = T[:, :, :3, :] @ self._local_h                                     # (S, B, 3, M)
        return X[:, self.point_body, :, self._point_index].transpose(1, 0, 2)

    def directions(self, T: np.ndarray, local: np.ndarray) -> np.ndarray:
        """(S, M, 3) vectors fixed in the points' bodies, local (M, 3) there, in the base frame at body poses T
        (S, B, 4, 4) (body_poses), e.g. surface normals."""
        X = T[:, :, :3, :3] @ np.asarray(local, float).T                     # (S, B, 3, M), as _apply
        return X[:, self.point_body, :, self._point_index].transpose(1, 0, 2)

    def points_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fit keypoints P (S, M, 3) in the base frame (metres) and dP/dq (S, M, 3, J): for each q-driven joint
        moving a point, gain * axis x (P - joint origin) (revolute) or gain * axis (prismatic)."""
        return self.points_and_jacobian_at(self.body_poses(q))

    def points_and_jacobian_at(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """points_and_jacobian from body poses T (S, B, 4, 4) already computed (body_poses), e.g. shared with
        directions."""
        P = self._apply(T)
        S, B, M = len(P), self.n_bodies, self.n_points
        Rw, o = T[:, :, :3, :3], T[:, :, :3, 3:]                              # (S, B, 3, 3), (S, B, 3, 1)
        # axis x (P - o) = [a]x P - [a]x o with [a]x = Rw [a_local]x Rw^T (zero for prismatic bodies, whose
        # column is the axis itself)
        skew = Rw @ self._skew_local @ np.swapaxes(Rw, -1, -2)
        const = Rw @ self._prismatic_axis - skew @ o                          # (S, B, 3, 1)
        D = (skew.reshape(S, 3 * B, 3) @ np.ascontiguousarray(P.transpose(0, 2, 1))).reshape(S, B, 3, M)
        D += const
        D *= self._coef                                                       # (S, B, 3, M)
        J = D.reshape(S, B, 3 * M).transpose(0, 2, 1) @ self._to_joint         # (S, 3M, J)
        # a (S, M, 3, J) view of component-major memory: swapaxes(1, 2) gives the contiguous (S, 3, M, J) back
        return P, J.reshape(S, 3, M, self.n_joints).swapaxes(1, 2)
