"""Generated videos (config/generate/video.yaml): clips in which one camera watches the robot move smoothly, frames
in order, each clip its own camera; a configuration that `extends` another gets the other's keys; the waypoint
path stays within the limits and moves smoothly. Real renders (Mesa EGL)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from holo_pose_ros.benchmark import TRACKING_HOLD, stream_frames
from holo_pose_ros.data.dream import DreamReader
from holo_pose_ros.data.generator import SETTINGS_FILE, generate, is_video_folder, load_generator_config
from holo_pose_ros.data.motion import waypoint_path


def test_a_video_config_extends_the_randomized_look():
    video, randomized = load_generator_config("video"), load_generator_config("randomized")
    assert "extends" not in video and video["video"]["clip_frames"] >= 2
    assert video["appearance"] == randomized["appearance"] and video["post"] == randomized["post"]
    assert video["camera"]["fill"] == randomized["camera"]["fill"]  # merged key by key
    assert video["camera"]["static_fill"] != randomized["camera"]["static_fill"]


def test_the_waypoint_path_is_smooth_and_within_the_limits():
    lower, upper = np.array([-2.0, 0.0, -0.5]), np.array([2.0, 0.04, 0.5])
    start = np.array([1.9, 0.02, 0.0])
    path = waypoint_path(lower, upper, start, 200, np.random.default_rng(0), (10, 20), 0.25)
    assert path.shape == (200, 3) and np.allclose(path[0], start)
    assert np.all(path >= lower - 1e-12) and np.all(path <= upper + 1e-12)
    assert np.all(np.abs(path - start) <= 0.25 * (upper - lower) + 1e-12)
    step = np.abs(np.diff(path, axis=0))
    assert step.max(axis=0) @ np.ones(3) > 0  # it moves
    assert np.all(step <= np.pi / 2 * 2 * 0.25 * (upper - lower) / 10 + 1e-12)  # eased legs of >= 10 frames
    with pytest.raises(ValueError):
        waypoint_path(lower, upper, start, 5, np.random.default_rng(0), (0, 3), 0.25)


def test_a_generated_video_holds_its_camera_within_a_clip_and_moves_the_robot_smoothly(tmp_path):
    config = {"extends": "video", "video": {"clip_frames": 4, "leg_frames": [3, 5], "reach": 0.1}}
    (tmp_path / "clips.yaml").write_text(yaml.safe_dump(config))
    generate("panda", 8, tmp_path / "video", seed=11, workers=1, progress=False, config=tmp_path / "clips.yaml")
    frames = list(DreamReader(tmp_path / "video", "panda"))
    assert [f.name for f in frames] == [f"{i:06d}" for i in range(8)]
    T = np.array([f.T_cam_base for f in frames])
    q = np.array([f.joints for f in frames])
    for clip in (slice(0, 4), slice(4, 8)):
        assert np.allclose(T[clip], T[clip][0], atol=1e-6)  # one camera per clip
        assert 0 < np.abs(np.diff(q[clip], axis=0)).max() < 0.5  # the robot moves, a little per frame
    assert not np.allclose(T[3], T[4], atol=1e-3)  # a new clip, a new camera
    again = tmp_path / "again"
    generate("panda", 8, again, seed=11, workers=1, progress=False, config=tmp_path / "clips.yaml")
    assert (again / "000005.rgb.jpg").read_bytes() == (tmp_path / "video" / "000005.rgb.jpg").read_bytes()
    # the benchmark plays a video in order, each frame once, however many frames it times
    assert is_video_folder(tmp_path / "video")
    chosen, hold = stream_frames(DreamReader(tmp_path / "video", "panda"), 6, tracking=True, cap=3)
    assert [f.name for f in chosen] == [f"{i:06d}" for i in range(6)] and hold == 1


def test_independent_frames_are_held_when_tracking(tmp_path):
    generate("panda", 3, tmp_path / "frames", seed=3, workers=1, progress=False)
    reader = DreamReader(tmp_path / "frames", "panda")
    assert not is_video_folder(tmp_path / "frames")
    assert stream_frames(reader, 100, tracking=True, cap=2)[1] == TRACKING_HOLD
    chosen, hold = stream_frames(reader, 100, tracking=False, cap=2)
    assert len(chosen) == 2 and hold == 1
    (tmp_path / "frames" / SETTINGS_FILE).write_text("not json")  # a damaged settings file: not a video
    assert not is_video_folder(tmp_path / "frames")
