"""Files written whole or not at all: what every writer of a file that a later run, a resume or the training reads
shares (checkpoints, config.yml, resume_command.txt, willags-process's outputs, the downscaled image folders, the
exported PLY and latents).

Each is written as a hidden sibling (`partial_path`) and renamed over its name when complete (`os.replace`, atomic
within a filesystem): a process killed or a disk filled mid-write leaves the previous file whole, never half of one.
Imports nothing of the package, so every folder may use it."""

import os
from pathlib import Path

PARTIAL_SUFFIX = ".partial"
"""Suffix of a file or folder being written (hidden, beside its final name)."""


def partial_path(path: Path) -> Path:
    """The hidden sibling `path` is written as before it is renamed: ``.<name>.<pid>.partial`` (one per process, so
    two writers never share one)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}{PARTIAL_SUFFIX}")


def write_text_atomic(path: Path, text: str) -> None:
    """Write a small text file atomically (its `partial_path` renamed over it), as UTF-8 whatever the locale; no
    partial file is left behind. Errors are the caller's to report."""
    tmp = partial_path(path)
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
