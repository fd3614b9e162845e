"""The one place a configured device name becomes a ``torch.device`` (the simulators' ``make_env``,
the jobs and ``l1flow-rl eval`` all read ``device=`` through it). Imports nothing of the package."""

from __future__ import annotations

import torch

__all__ = ["resolve_device"]


def resolve_device(device: str | torch.device) -> torch.device:
    """``"auto"``: CUDA when torch sees a GPU, else the CPU; any other name as ``torch.device`` reads
    it. A CUDA device this machine lacks is refused here, before anything is built.

    Example:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as err:  # torch's own message lists the device types it knows
        raise ValueError(f"device={str(device)!r} is not a device name: {err}") from None
    if resolved.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0 or (resolved.index is not None and resolved.index >= count):
            raise ValueError(
                f"device={str(device)!r}, but torch sees {count} CUDA device(s) on this machine; "
                "use device=cpu or device=auto"
            )
    return resolved
