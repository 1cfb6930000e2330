"""A checkpoint's digest: `payload_sha256`, stored in the checkpoint under `DIGEST`.

torch checks no checksum of its own when it loads a file (not even the zip's CRCs), so a
changed byte in a weight, an Adam moment or an RNG state would load as another number and
a resume would continue from it. The digest is taken over the fields as they read, not
over torch's bytes, so that it reads back the same whatever torch's serialization; every
reader verifies it (`mpnode_cli.training.checkpoint.read_checkpoint`). A file saved before
it has none and reads as before (`mpnode check` says so); an older mpnode ignores the
field, hence no new format version.
"""

from __future__ import annotations

import hashlib
from typing import Any

import torch

DIGEST = "payload_sha256"


def payload_sha256(payload: dict[str, Any]) -> str:
    """sha256 of a checkpoint's fields but `DIGEST`, by structure: each tensor's dtype,
    shape and bytes, other values by type and repr, dicts in their order."""
    digest = hashlib.sha256()

    def add(value: Any) -> None:
        if isinstance(value, torch.Tensor):
            flat = value.detach().cpu().contiguous().reshape(-1)
            digest.update(f"T{value.dtype}{list(value.shape)}".encode())
            digest.update(flat.view(torch.uint8).numpy())
        elif isinstance(value, dict):
            digest.update(b"{%d" % len(value))
            for key, item in value.items():
                add(key)
                add(item)
        elif isinstance(value, list | tuple):
            digest.update(b"[%d" % len(value))
            for item in value:
                add(item)
        else:
            digest.update(f"{type(value).__name__}:{value!r};".encode())

    add({key: value for key, value in payload.items() if key != DIGEST})
    return digest.hexdigest()
