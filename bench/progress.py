"""The one progress bar of long bench work (tqdm, on stderr, with rate and ETA)."""

from __future__ import annotations

from typing import Any

__all__ = ["progress_bar"]


def progress_bar(enabled: bool, total: int, description: str, unit: str) -> Any:
    """A tqdm progress bar over ``total`` units (a disabled one when ``enabled`` is false, so
    callers update it unconditionally). No monitor thread: pool workers are forked from this
    process."""
    from tqdm import tqdm

    tqdm.monitor_interval = 0
    return tqdm(total=total, desc=description, unit=unit, disable=not enabled,
                dynamic_ncols=True)
