"""``--device auto|cpu|cuda`` (:attr:`services.runtime.config.RunSettings.device`) as a torch device.

``auto`` is cuda where torch sees a CUDA device and the run's method runs there
(:attr:`causal.method.Method.devices`), cpu otherwise. ``cuda`` where there is none, or for a method
that runs on CPU only, is a configuration error (``ValueError``): the supervisor's preflight refuses
the run with exit 2, a service started on its own exits 78 before it opens the bus.

Whatever the device, what leaves a process is on the CPU: weights are exported as numpy arrays and
checkpoints hold CPU tensors (:func:`services.runtime.checkpoint.save_checkpoint`), so a checkpoint
written on a GPU machine loads on one without.
"""
from __future__ import annotations

from typing import Callable

import torch

DEVICES = ("auto", "cpu", "cuda")


def resolve_device(name: str, supported: tuple[str, ...] = ("cpu", "cuda"),
                   cuda_available: Callable[[], bool] | None = None) -> torch.device:
    """The torch device ``--device name`` means here for a method that runs on ``supported``
    (``cuda_available``: ``torch.cuda.is_available``, asked when needed)."""
    cuda_available = cuda_available or torch.cuda.is_available
    if name not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(repr(d) for d in DEVICES)}; got {name!r}")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" and not cuda_available():
        raise ValueError(f"--device cuda: torch sees no CUDA device here (torch {torch.__version__}, built for "
                         f"CUDA {torch.version.cuda or 'none'}); use --device auto or cpu")
    if name == "cuda" and "cuda" not in supported:
        raise ValueError("--device cuda: this run's method runs on the CPU only; use --device auto or cpu")
    return torch.device("cuda" if "cuda" in supported and cuda_available() else "cpu")
