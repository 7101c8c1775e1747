"""Episode checkpoints: one file rewritten atomically after every finished round.

A killed episode resumes from the last finished round; the file also holds the fingerprint of the
config it was made with, so a resume under a different config fails instead of mixing runs.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

CHECKPOINT = "episode.pt"


def fingerprint(config: dict) -> str:
    """A stable hash of a JSON-able config."""
    text = json.dumps(config, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save_checkpoint(folder: Path, state: dict) -> Path:
    """Write ``state`` to folder/episode.pt atomically (temp file + rename): never half-written."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / CHECKPOINT
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(folder: Path | None, expected_fingerprint: str) -> dict | None:
    """The saved state, or None when there is none; a mismatched config is an error."""
    if folder is None or not (folder / CHECKPOINT).exists():
        return None
    path = folder / CHECKPOINT
    try:
        state = torch.load(path, weights_only=False)
    except Exception as err:
        raise ValueError(f"{path}: unreadable checkpoint ({type(err).__name__}: {err}); "
                         "delete it to start the episode afresh") from None
    if state.get("fingerprint") != expected_fingerprint:
        raise ValueError(f"{path}: checkpoint was written for a different config "
                         f"({state.get('fingerprint')} != {expected_fingerprint}); use another "
                         "checkpoint folder or delete it")
    return state
