"""The estimator node's log throttle (found by the fuzz, scripts/fuzz_node.py): a repeated problem was logged
again whenever its text changed, so reasons that alternate (data too short, encoding unsupported, data too
short...) or carry numbers (data is 1000 bytes, then 1200) wrote one line per message. A reason is now its text
without the particulars, logged at once the first time and then once per LOG_PERIOD_S with the count held back."""

from __future__ import annotations

from holo_pose_ros.nodes.estimator_node import LOG_PERIOD_S, LogThrottle, reason_template


def test_reason_template_blanks_the_particulars():
    assert reason_template("data is 1000 bytes; step 960 x height 240 needs 230400") == \
        reason_template("data is 12 bytes; step 3 x height 1 needs 3")
    assert reason_template("unsupported image encoding 'yuv422'") == reason_template("unsupported image encoding ''")
    assert reason_template("CameraInfo.k is not finite: [nan, 0.0]") == "CameraInfo.k is not finite: [...]"
    assert reason_template("fx = -3.5e+02, fy = inf") == "fx = N, fy = N"
    assert reason_template("rgb8 and CameraInfo") == "rgb8 and CameraInfo"  # words keep their digits and 'inf'
    assert reason_template("data is 1 bytes") != reason_template("empty image: 0 x 0 px")


def test_log_throttle_logs_each_reason_once_per_period_even_when_reasons_alternate():
    throttle = LogThrottle(period_s=LOG_PERIOD_S)
    a, b = "data is 10 bytes; step 3 x height 2 needs 6", "unsupported image encoding 'x'"
    logged = [throttle.check("image", detail, t * 0.1) for t, detail in enumerate([a, b] * 20)]  # 4 s, alternating
    assert logged[:2] == [0, 0] and all(x is None for x in logged[2:])
    # after a period, one line per reason again, with the count held back meanwhile
    assert throttle.check("image", a.replace("10", "99"), LOG_PERIOD_S + 0.1) == 19
    assert throttle.check("image", b, LOG_PERIOD_S + 0.2) == 19
    assert throttle.check("camera_info", a, 0.5) == 0  # keys are independent
    assert throttle.check("no_camera_info", "", 0.0) == 0 and throttle.check("no_camera_info", "", 1.0) is None


def test_log_throttle_forgets_the_oldest_reasons_beyond_its_memory():
    throttle = LogThrottle(period_s=5.0, max_reasons=2)
    assert [throttle.check("k", r, 0.0) for r in ("a", "b", "c")] == [0, 0, 0]
    assert throttle.check("k", "a", 0.1) == 0  # forgotten: logged again
    assert throttle.check("k", "c", 0.2) is None
