"""Where the tensors go: `torch_device(name)`, the one check of a `--device` name.

A user names a device; asking for CUDA where torch sees none is refused in one line before
any work, instead of failing later inside torch with its own message.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

DEVICES = ("cpu", "cuda")


def torch_device(name: str) -> torch.device:
    """The device `--device NAME` asks for.

    Raises:
        ValueError: a name other than cpu or cuda, or cuda where torch sees no CUDA device
            (one line).
    """
    import torch

    if name not in DEVICES:
        raise ValueError(f"unknown device '{name}' ({' or '.join(DEVICES)})")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but torch sees no CUDA device")
    return torch.device(name)
