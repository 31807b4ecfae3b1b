"""The benchmark measures the real pipeline and reports the figures the speed work is judged by."""

import json

import pytest

from holo_pose_ros.cli import main
from holo_pose_ros.data.generator import generate


def test_benchmark_reports_stages_and_figures(tmp_path, small_model_card, capsys):
    generate("panda", 2, tmp_path / "frames", seed=4, workers=1, progress=False)
    out = tmp_path / "bench.json"
    assert main(["benchmark", "--model", str(small_model_card), "--data", str(tmp_path / "frames"), "--frames", "4",
                 "--fit", "--parts", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    for key in ("fps", "latency_ms_p50", "latency_ms_p95", "gflops", "params_m", "peak_rss_mb", "device", "backend"):
        assert key in result
    stages = result["stages_ms"]
    assert set(stages) == {"image_conversion", "localize", "crop", "network", "kinematics", "lifter", "fit", "in_view",
                           "messages", "total"}
    assert result["fit"] is True and result["parts"] is True and stages["fit"]["p50"] > 0
    assert stages["total"]["p50"] >= stages["network"]["p50"] > 0 and result["gflops"] > 0
    assert abs(result["fps"] - 1e3 / stages["total"]["mean"]) < 1e-6
    printed = capsys.readouterr().out
    assert "frames/s" in printed and "fitted by parts" in printed
    assert main(["benchmark", "--model", str(small_model_card), "--data", str(tmp_path / "frames"), "--frames", "2",
                 "--fit", "--static-camera", "--json", str(out)]) == 0  # its stage is timed
    static = json.loads(out.read_text())
    assert static["static_camera"] is True and static["stages_ms"]["static_camera"]["p50"] > 0


@pytest.mark.parametrize("flags", [[], ["--no-pipeline"]])
def test_node_figure_times_the_estimator_node_in_a_real_graph(tmp_path, small_model_card, capsys, flags):
    generate("panda", 2, tmp_path / "frames", seed=5, workers=1, progress=False)
    out = tmp_path / "bench.json"
    assert main(["benchmark", "--model", str(small_model_card), "--data", str(tmp_path / "frames"), "--frames", "6",
                 "--backend", "onnxruntime", "--node", "--node-rate", "5", "--json", str(out), *flags]) == 0
    result = json.loads(out.read_text())
    assert result["node"]["pipeline"] is not bool(flags)
    assert result["backend"] == "onnxruntime"
    node = result["node"]
    assert node["sent"] == 6 and node["answered"] + node["dropped"] == 6 and node["answered"] >= 1
    # an answer cannot come before its image: at least the in-process estimate's time
    assert result["stages_ms"]["network"]["p50"] < node["latency_ms_p50"] <= node["latency_ms_p95"] <= node["latency_ms_max"]
    printed = capsys.readouterr().out
    assert "image published -> JointState received" in printed
    assert ("one thread" if flags else "pipelined") in printed
