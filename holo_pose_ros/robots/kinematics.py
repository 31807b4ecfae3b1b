"""RobotModel: batched, differentiable forward kinematics (pytorch-kinematics) of one robot spec, giving named
link transforms and the DREAM keypoints in the base frame or in the root keypoint's frame. Metres, radians."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import numpy as np
import pytorch_kinematics as pk
import torch
import yourdfpy

from holo_pose_ros.robots.description import urdf_file, urdf_text
from holo_pose_ros.robots.spec import RobotSpec, load_robot_spec


@contextlib.contextmanager
def _quiet_stderr():
    """pytorch-kinematics' URDF parser prints 'Unknown attribute' for harmless tags (dynamics, materials) on the C
    stderr; hide that noise while parsing."""
    fd = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
                yield
    finally:
        os.dup2(fd, 2)
        os.close(fd)


def load_urdf_model(spec: RobotSpec) -> yourdfpy.URDF:
    """The spec's URDF parsed by yourdfpy, without meshes (joint limits, mimics, visuals' file names)."""
    path = urdf_file(spec.urdf)
    if path is None:
        return yourdfpy.URDF.load(io.StringIO(spec.urdf.string), build_scene_graph=False, load_meshes=False)
    return yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False)


class RobotModel:
    """Forward kinematics of the estimated joints q (B x J, YAML order) of one robot.

    Mimic joints follow their leader (value = multiplier * leader + offset); URDF joints that are neither
    estimated nor mimics stay at `fixed_joints` (or 0). Every output is differentiable with respect to q.
    """

    def __init__(self, spec: RobotSpec | str | Path, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"):
        self.spec = load_robot_spec(spec) if not isinstance(spec, RobotSpec) else spec
        self.dtype, self.device = dtype, torch.device(device)
        self.urdf = load_urdf_model(self.spec)
        path = urdf_file(self.spec.urdf)
        self.urdf_dir: Path | None = path.parent if path is not None else None
        with _quiet_stderr():
            self.chain = pk.build_chain_from_urdf(urdf_text(self.spec.urdf).encode()).to(dtype=dtype, device=self.device)
        self._pk_joint_names: list[str] = self.chain.get_joint_parameter_names()
        joints = self.urdf.joint_map
        links = set(self.urdf.link_map)
        for k in self.spec.fit_keypoints:
            if k.link not in links:
                raise ValueError(f"{self.spec.source_file}: keypoint '{k.name}' names link '{k.link}', not in the URDF")
        if self.spec.base_link not in links:
            raise ValueError(f"{self.spec.source_file}: base_link '{self.spec.base_link}' is not in the URDF")

        estimated = {j.urdf: i for i, j in enumerate(self.spec.joints)}
        for j in self.spec.joints:
            if j.urdf not in joints or joints[j.urdf].type == "fixed":
                raise ValueError(f"{self.spec.source_file}: joint '{j.name}' -> '{j.urdf}' is not a movable URDF joint")
        # Each pk input column is: (index into q or -1, multiplier, offset).
        source, mult, offset = [], [], []
        for name in self._pk_joint_names:
            joint = joints[name]
            lead, m, o = name, 1.0, 0.0
            if joint.mimic is not None:
                lead, m, o = joint.mimic.joint, float(joint.mimic.multiplier or 1.0), float(joint.mimic.offset or 0.0)
            if lead in estimated:
                source.append(estimated[lead]); mult.append(m); offset.append(o)
            else:
                source.append(-1); mult.append(0.0); offset.append(m * self.spec.fixed_joints.get(lead, 0.0) + o)
        self._source = torch.tensor(source, dtype=torch.long)
        self._mult = torch.tensor(mult, dtype=dtype, device=self.device)
        self._offset = torch.tensor(offset, dtype=dtype, device=self.device)

        lower, upper = [], []
        for j in self.spec.joints:
            lim = joints[j.urdf].limit
            if lim is None or lim.lower is None or lim.upper is None:
                raise ValueError(f"{self.spec.source_file}: URDF joint '{j.urdf}' has no limits")
            lower.append(float(lim.lower)); upper.append(float(lim.upper))
        self.lower = torch.tensor(lower, dtype=dtype, device=self.device)
        self.upper = torch.tensor(upper, dtype=dtype, device=self.device)
        self.neutral = torch.tensor(self.spec.neutral, dtype=dtype, device=self.device)
        self.joint_types = [joints[j.urdf].type for j in self.spec.joints]
        self._keypoint_links = [k.link for k in self.spec.keypoints]
        fit = self.spec.fit_keypoints
        self._fit_links = list(dict.fromkeys(k.link for k in fit))
        self._fit_link_index = torch.tensor([self._fit_links.index(k.link) for k in fit], device=self.device)
        self._fit_offsets = torch.tensor([k.xyz for k in fit], dtype=dtype, device=self.device).reshape(-1, 3)
        children = {j.child for j in self.urdf.robot.joints}
        roots = [link for link in self.urdf.link_map if link not in children]
        if len(roots) != 1:
            raise ValueError(f"{self.spec.source_file}: the URDF must be one tree, found roots {roots}")
        self.urdf_root: str = roots[0]

    # -- names and sizes -------------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def joint_names(self) -> list[str]:
        return self.spec.joint_names

    @property
    def keypoint_names(self) -> list[str]:
        return self.spec.keypoint_names

    @property
    def root_index(self) -> int:
        return self.spec.root_index

    @property
    def n_joints(self) -> int:
        return len(self.spec.joints)

    @property
    def n_keypoints(self) -> int:
        return len(self.spec.keypoints)

    @property
    def n_fit_keypoints(self) -> int:
        """DREAM's keypoints plus the YAML's extra fit points."""
        return len(self.spec.fit_keypoints)

    @property
    def fit_keypoint_names(self) -> list[str]:
        return [k.name for k in self.spec.fit_keypoints]

    @property
    def link_names(self) -> list[str]:
        return list(self.urdf.link_map)

    @property
    def keypoint_parents(self) -> list[int]:
        """For each keypoint, the index of the nearest keypoint up the kinematic tree (-1 for none): the
        skeleton's edges, for drawing."""
        parent_of = {j.child: j.parent for j in self.urdf.robot.joints}
        index = {link: i for i, link in enumerate(self._keypoint_links)}
        parents = []
        for link in self._keypoint_links:
            up = parent_of.get(link)
            while up is not None and up not in index:
                up = parent_of.get(up)
            parents.append(index[up] if up is not None else -1)
        return parents

    def close_up_fit_indices(self) -> dict[str, np.ndarray]:
        """For each of the YAML's `close_ups`, the indices of the fit keypoints on the links of its subtree (the
        part's link and every link below it). ValueError naming the YAML for a link the URDF lacks."""
        below: dict[str, list[str]] = {}
        for joint in self.urdf.robot.joints:
            below.setdefault(joint.parent, []).append(joint.child)
        links = [k.link for k in self.spec.fit_keypoints]
        out = {}
        for name, top in self.spec.close_ups.items():
            if top not in self.urdf.link_map:
                raise ValueError(f"{self.spec.source_file}: close-up '{name}' starts at link '{top}', which the URDF "
                                 "does not have")
            subtree, stack = set(), [top]
            while stack:
                link = stack.pop()
                subtree.add(link)
                stack.extend(below.get(link, []))
            out[name] = np.array([i for i, link in enumerate(links) if link in subtree], dtype=int)
        return out

    # -- kinematics ------------------------------------------------------------------------------------------
    def _as_batch(self, q) -> torch.Tensor:
        q = torch.as_tensor(q, dtype=self.dtype, device=self.device)
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise ValueError(f"{self.name}: expected joints of shape (B, {self.n_joints}), got {tuple(q.shape)}")
        return q

    def full_configuration(self, q: torch.Tensor) -> torch.Tensor:
        """(B, J) estimated joints -> (B, P) values of every pytorch-kinematics joint (mimics and fixed set)."""
        q = self._as_batch(q)
        gathered = q[:, self._source.clamp(min=0)] * (self._source >= 0).to(q.dtype)
        return gathered * self._mult + self._offset

    def link_transforms(self, q: torch.Tensor, links: list[str] | None = None) -> dict[str, torch.Tensor]:
        """Named link poses T_base<-link (B, 4, 4) in the spec's base_link frame; all links when `links` is None."""
        wanted = list(dict.fromkeys((links or self.link_names) + [self.spec.base_link]))
        idx = self.chain.get_frame_indices(*wanted)
        fk = self.chain.forward_kinematics(self.full_configuration(q), frame_indices=idx)
        mats = {name: fk[name].get_matrix() for name in wanted}
        if self.spec.base_link != self.urdf_root:
            inv_base = torch.linalg.inv(mats[self.spec.base_link])
            mats = {k: inv_base @ v for k, v in mats.items()}
        return {k: mats[k] for k in (links or self.link_names)}

    def keypoints(self, q: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) keypoints (link-frame origins) in the base frame, metres."""
        mats = self.link_transforms(q, self._keypoint_links)
        return torch.stack([mats[link][:, :3, 3] for link in self._keypoint_links], dim=1)

    def fit_keypoints(self, q: torch.Tensor) -> torch.Tensor:
        """(B, M, 3) fit keypoints in the base frame, metres: each point's link pose applied to its offset. The
        first N are DREAM's keypoints."""
        mats = self.link_transforms(q, self._fit_links)
        T = torch.stack([mats[link] for link in self._fit_links], dim=1)[:, self._fit_link_index]  # (B, M, 4, 4)
        return (T[..., :3, :3] @ self._fit_offsets[None, :, :, None])[..., 0] + T[..., :3, 3]

    def fit_keypoints_in_camera(self, q: torch.Tensor, T_cam_base: torch.Tensor) -> torch.Tensor:
        """(B, M, 3) fit keypoints in the camera frame, given the base pose T_cam<-base (B, 4, 4)."""
        kp = self.fit_keypoints(q)
        T = torch.as_tensor(T_cam_base, dtype=kp.dtype, device=kp.device).reshape(-1, 4, 4)
        return kp @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]

    def root_transform(self, q: torch.Tensor) -> torch.Tensor:
        """T_base<-root (B, 4, 4): the root keypoint's link frame in the base frame."""
        return self.link_transforms(q, [self._keypoint_links[self.root_index]])[self._keypoint_links[self.root_index]]

    def keypoints_in_root(self, q: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) keypoints expressed in the root keypoint's link frame (the frame RotationNet predicts)."""
        mats = self.link_transforms(q, self._keypoint_links)
        root_inv = torch.linalg.inv(mats[self._keypoint_links[self.root_index]])
        return torch.stack([(root_inv @ mats[link])[:, :3, 3] for link in self._keypoint_links], dim=1)

    def keypoints_in_camera(self, q: torch.Tensor, T_cam_base: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) keypoints in the camera frame, given the base pose T_cam<-base (B, 4, 4)."""
        kp = self.keypoints(q)
        T = torch.as_tensor(T_cam_base, dtype=kp.dtype, device=kp.device).reshape(-1, 4, 4)
        return kp @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]

    def clamp(self, q: torch.Tensor) -> torch.Tensor:
        """q clamped to the URDF joint limits."""
        return torch.maximum(torch.minimum(self._as_batch(q), self.upper), self.lower)

    def sample_uniform(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """(n, J) joints drawn uniformly within the URDF limits."""
        u = torch.rand(n, self.n_joints, generator=generator, dtype=self.dtype).to(self.device)
        return self.lower + u * (self.upper - self.lower)
