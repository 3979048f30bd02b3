"""A training run's fingerprint on CPU, to show that a refactor left behaviour unchanged.

On CPU training is deterministic, so two commits that behave the same print the same numbers to the last digit
(on the GPU, gsplat's backward accumulates with atomics: two runs of one commit with one seed differ by up to 0.8 dB
after 5000 steps on fox-wild, docs/architecture.md). 20 steps of nerfstudio's Trainer on the embedded default scene
with tests/test_train.py's settings, torch seed 0, for the default and a paper-like configuration (colour decoder,
VAE, tri-plane field, unfused teacher). Compare two commits by running it in a checkout of each:

    git worktree add --detach /tmp/old 022d2a9
    (cd /tmp/old && PYTHONPATH=$PWD python $REPO/benchmarks/behaviour_fingerprint.py)
    python -m benchmarks fingerprint
"""

import sys
import tempfile
from pathlib import Path

import torch

CONFIGS = {
    "default": {},
    "paper-like": {"color_mode": "decoder", "latent.kind": "vae", "use_field": True, "mask.teacher.fused": False},
}
"""Model overrides of each fingerprinted configuration."""


def fingerprint(name: str, out: Path, steps: int = 20) -> str:
    """One line: the configuration's last loss, the sum of its losses and the sum of its Gaussians' means."""
    sys.path.insert(0, str(Path.cwd()))  # the checkout being fingerprinted: its tests/ and willags_ns/
    from tests.test_train import _train

    torch.manual_seed(0)
    _, trainer, losses = _train(out / name, "willags", steps=steps, **CONFIGS[name])
    m = trainer.pipeline.model
    total = sum(v for v, _ in losses)
    return f"{name}: last loss {losses[-1][0]!r}, sum of losses {total!r}, sum of means {float(m.means.sum())!r}"


def main() -> int:
    # one folder for every run: nerfstudio's event writer is process-global and keeps the first run's file open
    with tempfile.TemporaryDirectory() as d:
        for n in CONFIGS:
            print(fingerprint(n, Path(d)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
