"""The network as an ONNX graph, run by ONNX Runtime: export (torch's TorchScript exporter, dynamic batch), a cache
of exported models keyed by the weights' hash, and `OnnxNetwork`, a drop-in for HolisticNet's forward (same inputs,
same named outputs as torch tensors). Forward kinematics stays in torch (pytorch-kinematics), outside the graph."""

from __future__ import annotations

import contextlib
import copy
import hashlib
import logging
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from holo_pose_ros import __version__
from holo_pose_ros.model.network import HolisticNet, Localizer, example_inputs
from holo_pose_ros.model.cards import read_card

LOG = logging.getLogger(__name__)
OPSET = 18
INPUTS = ("image", "K_crop")
LIFTER_INPUTS = ("uv", "confidence", "box", "K")


def export_onnx(net: HolisticNet, path: str | Path) -> Path:
    """Write `net` in eval mode as one self-contained ONNX file with a dynamic batch dimension. The export runs on
    a CPU copy: the caller's network stays on its device and in its mode."""
    net = copy.deepcopy(net).cpu().eval()
    example = example_inputs(net.cfg.input_size, batch=2)
    with torch.inference_mode():
        names = list(net(*example).keys())  # the forward's output keys name the graph's outputs
    return export_module(net, example, path, INPUTS, names)


def export_localizer(net: HolisticNet, size: int, path: str | Path) -> Path:
    """Write `net`'s 2D-only localize pass (model/network.py Localizer) at an input of `size` px as one ONNX file
    with the input 'image' and a dynamic batch; like export_onnx, on a CPU copy in eval mode."""
    localizer = Localizer(copy.deepcopy(net).cpu().eval()).eval()
    example = (example_inputs(size, batch=2)[0],)
    with torch.inference_mode():
        names = list(localizer(*example).keys())
    return export_module(localizer, example, path, ("image",), names)


class LifterGraph(torch.nn.Module):
    """The lifter's hypotheses as one graph, features, MLP and pose decoding together: (uv (B, M, 2) image px,
    confidence (B, M), box (B, 3), K (B, 3, 3)) -> (joints (B, H, J), T_cam_base (B, H, 4, 4)), float32."""

    def __init__(self, lifter: torch.nn.Module):
        super().__init__()
        self.lifter = lifter

    def forward(self, uv: torch.Tensor, confidence: torch.Tensor, box: torch.Tensor, K: torch.Tensor):
        return self.lifter.hypotheses(uv, confidence, box, K)


def export_lifter(lifter: torch.nn.Module, path: str | Path) -> Path:
    """Write `lifter`'s hypotheses (LifterGraph) in eval mode as one ONNX file with a dynamic batch, on a CPU copy.
    Its inputs are 'uv', 'confidence', 'box', 'K' and its outputs 'joints' and 'T_cam_base'."""
    graph = LifterGraph(copy.deepcopy(lifter).cpu().float().eval()).eval()
    M = lifter.n_fit_keypoints
    box = torch.tensor([[100.0, 80.0, 300.0], [40.0, 20.0, 200.0]])
    K = torch.tensor([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]).expand(2, 3, 3).contiguous()
    example = (box[:, None, :2] + torch.rand(2, M, 2) * box[:, None, 2:], torch.rand(2, M), box, K)
    return export_module(graph, example, path, LIFTER_INPUTS, ["joints", "T_cam_base"])


def export_module(module: torch.nn.Module, example: tuple[torch.Tensor, ...], path: str | Path,
                  input_names: tuple[str, ...], output_names: list[str]) -> Path:
    """Write a CPU module in eval mode (as given) as one self-contained ONNX file, the first dimension of every input
    and output a dynamic batch; written to a temporary name and renamed, so a crash never leaves a truncated file.

    TorchScript's exporter, not dynamo's: the same graph for ONNX Runtime (outputs within 1e-4, the same pass time)
    written in about 1 s instead of 15-45 s, which every user's first run of a model and every fresh test session
    paid once per graph (7 December 2026, docs/speed.md). torch deprecates it; `dynamo=True` is the way back."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with warnings.catch_warnings(), _quiet_loggers("torch.onnx"):
        warnings.simplefilter("ignore")  # the exporter's deprecation and tracing chatter, not the user's concern
        torch.onnx.export(module, example, str(tmp), dynamo=False, opset_version=OPSET, input_names=list(input_names),
                          output_names=output_names, verbose=False,
                          dynamic_axes={n: {0: "batch"} for n in (*input_names, *output_names)})
    os.replace(tmp, path)
    return path


def session(path: str | Path, threads: int | None = None, providers: list | None = None):
    """An ONNX Runtime session of `path` with every graph optimization, sequential execution, `threads` intra-op
    threads (default: ONNX Runtime's, one per physical core) and no busy-waiting after a run: spinning threads held
    the cores that the lifter and the fit need next (the lifter's p95 was 13 ms with spinning, its p50 1.7 ms)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads:
        options.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), options, providers=providers or ["CPUExecutionProvider"])


@contextlib.contextmanager
def _quiet_loggers(*names: str):
    """Raise these libraries' loggers to ERROR for the duration (the exporter logs every pass at INFO/WARNING)."""
    loggers = [logging.getLogger(name) for name in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def cache_dir() -> Path:
    """$XDG_CACHE_HOME/holo_pose_ros/onnx (default ~/.cache/...)."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "holo_pose_ros" / "onnx"


def _cached(card_path: Path, card: dict, name: str, export) -> Path:
    """The cached ONNX file of a card: named `name`, the package version and the hash of card and weights, so new
    weights or new code never run a stale graph; `export(path)` writes it when missing."""
    digest = hashlib.sha256(card_path.read_bytes())
    digest.update((card_path.parent / card["weights"]).read_bytes())
    path = cache_dir() / f"{name}-{__version__}-{digest.hexdigest()[:16]}.onnx"
    if not path.is_file():
        LOG.info("exporting %s to ONNX (once): %s", card_path, path)
        export(path)
    return path


def cached_export(net: HolisticNet, model: str | Path, localize_size: int | None = None) -> Path:
    """The ONNX export of `model` (a shipped name or a card/weights path; `net` is its loaded network), made once
    and reused (`_cached`). With `localize_size` (px): the export of its 2D-only localize pass at that input
    instead."""
    card_path, card = read_card(model)
    part = "" if localize_size is None else f"-localize{int(localize_size)}"
    if localize_size is None:
        export = lambda path: export_onnx(net, path)  # noqa: E731
    else:
        export = lambda path: export_localizer(net, int(localize_size), path)  # noqa: E731
    return _cached(card_path, card, f"{card['robot']}-{card['model']['name']}{part}", export)


def cached_lifter_export(lifter: torch.nn.Module, card_path: str | Path) -> Path:
    """The ONNX export of the lifter whose card is `card_path` (`lifter` is it, loaded), made once and reused
    (`_cached`)."""
    from holo_pose_ros.model.cards import read_card_file
    from holo_pose_ros.model.lifter import resolve_lifter

    card_path = resolve_lifter(card_path)
    return _cached(card_path, read_card_file(card_path), card_path.stem, lambda path: export_lifter(lifter, path))


def has_cuda_provider() -> bool:
    """Whether the installed onnxruntime can run on a GPU (the onnxruntime-gpu build)."""
    import onnxruntime as ort

    return "CUDAExecutionProvider" in ort.get_available_providers()


class OnnxNetwork:
    """An ONNX Runtime session with HolisticNet's call signature: (image (B, 3, S, S) in [0, 1], K_crop (B, 3, 3))
    -> dict of named torch tensors on the CPU; or its Localizer's, (image,). All graph optimizations on; `threads` intra-op threads (default:
    ONNX Runtime's, one per physical core)."""

    def __init__(self, path: str | Path, device: str | torch.device = "cpu", threads: int | None = None):
        device = torch.device(device)
        if device.type == "cuda":
            if not has_cuda_provider():
                raise ValueError("this onnxruntime has no CUDA provider (install onnxruntime-gpu), or use the torch "
                                 "backend on CUDA")
            providers = [("CUDAExecutionProvider", {"device_id": device.index or 0}), "CPUExecutionProvider"]
        else:
            providers = ["CPUExecutionProvider"]
        self.path = Path(path)
        self.session = session(self.path, threads, providers)
        self.names = [o.name for o in self.session.get_outputs()]
        self.inputs = [i.name for i in self.session.get_inputs()]

    def __call__(self, *inputs: torch.Tensor) -> dict[str, torch.Tensor]:
        """The graph's inputs in order (the network: image, K_crop; its localizer: image)."""
        if len(inputs) != len(self.inputs):
            raise ValueError(f"{self.path.name} takes {len(self.inputs)} inputs ({', '.join(self.inputs)}), got {len(inputs)}")
        feeds = {name: np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)
                 for name, x in zip(self.inputs, inputs)}
        return {name: torch.from_numpy(value) for name, value in zip(self.names, self.session.run(None, feeds))}
