"""Placed, not only registered: an SfM model's cameras against the true poses of a synthetic collection.

    python -m benchmarks placement --truth SRC/colmap/sparse/0 --model SCENE/colmap/sparse/0

The model's camera centres are aligned to the true centres by one similarity (Umeyama, least squares over every
photo in both); a centre's error is its distance to the true centre relative to the scene's radius (the true
centres' median distance to their centroid). A photo is *placed* when it is registered, its centre error is at most
``tolerance`` (5 % of the radius) and its rotation error (after the same alignment) at most ``max_rotation_deg``.
The pairwise distances' correlation tells a folded model (registered, placed nowhere) from a noisy one.
"""

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from willags_ns.tools.sfm import model_w2c, rotation_errors_deg, umeyama

HOW = (
    "camera centres similarity-aligned (Umeyama) to the scene's true centres; errors relative to the true centres'"
    " median distance to their centroid"
)


def placement(
    est_w2c: dict[str, np.ndarray],
    true_w2c: dict[str, np.ndarray],
    tolerance: float = 0.05,
    max_rotation_deg: float = 5.0,
) -> dict[str, Any]:
    """How many photos an SfM model placed: poses are world-to-camera [4, 4] keyed by image name (any convention, the
    same on both sides); ``true_w2c`` holds every photo of the collection, ``est_w2c`` the registered ones.

    Returns ``compared`` (photos in both), ``median_center_error_rel`` / ``max_center_error_rel`` (relative to the
    scene's radius), ``within_5pct`` (the fraction of the compared photos with a centre error <= ``tolerance``),
    ``median_rotation_error_deg`` / ``max_rotation_error_deg``, ``placed`` (the fraction of ALL true photos that
    are registered, within ``tolerance`` and within ``max_rotation_deg``), ``pairwise_distance_correlation`` and
    ``how``. Raises ValueError with fewer than 3 photos in both.
    """
    names = sorted(set(est_w2c) & set(true_w2c))
    if len(names) < 3:
        raise ValueError(f"need >= 3 photos in both the model and the truth to align them, got {len(names)}")
    est_c2w = np.stack([np.linalg.inv(np.asarray(est_w2c[n], float)) for n in names])
    true_c2w = np.stack([np.linalg.inv(np.asarray(true_w2c[n], float)) for n in names])
    x, y = est_c2w[:, :3, 3], true_c2w[:, :3, 3]
    scale, rot, shift = umeyama(x, y)
    radius = float(np.median(np.linalg.norm(y - y.mean(0), axis=1)))
    err = np.linalg.norm(scale * x @ rot.T + shift - y, axis=1) / max(radius, 1e-12)
    rot_err = rotation_errors_deg(true_c2w[:, :3, :3], rot @ est_c2w[:, :3, :3])
    iu = np.triu_indices(len(names), 1)
    dx = np.linalg.norm(x[:, None] - x[None], axis=-1)[iu]
    dy = np.linalg.norm(y[:, None] - y[None], axis=-1)[iu]
    placed = (err <= tolerance) & (rot_err <= max_rotation_deg)
    return {
        "compared": len(names),
        "total": len(true_w2c),
        "median_center_error_rel": float(np.median(err)),
        "max_center_error_rel": float(err.max()),
        "within_5pct": float((err <= tolerance).mean()),
        "median_rotation_error_deg": float(np.median(rot_err)),
        "max_rotation_error_deg": float(rot_err.max()),
        "placed": float(placed.sum() / len(true_w2c)),
        "placed_rule": f"registered, centre error <= {tolerance:g} of the radius, rotation error <= "
        f"{max_rotation_deg:g} deg",
        "pairwise_distance_correlation": float(np.corrcoef(dx, dy)[0, 1]),
        "how": HOW,
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks placement", description=__doc__.split("\n\n")[0])
    parser.add_argument("--truth", required=True, help="the COLMAP model of the true poses (e.g. SRC/colmap/sparse/0)")
    parser.add_argument("--model", required=True, help="the SfM model to judge (e.g. SCENE/colmap/sparse/0)")
    parser.add_argument("--tolerance", type=float, default=0.05, help="centre error allowed, share of the radius")
    parser.add_argument("--max-rotation-deg", type=float, default=5.0, help="rotation error allowed, degrees")
    args = parser.parse_args(list(argv) if argv is not None else sys.argv[1:])
    models = {}
    for what in ("truth", "model"):
        try:
            models[what] = model_w2c(getattr(args, what))
        except Exception as exc:  # pycolmap raises bare RuntimeErrors/ValueErrors on a missing or broken model
            print(f"benchmarks placement: cannot read the {what} model {getattr(args, what)}: {exc}", file=sys.stderr)
            return 2
    try:
        result = placement(models["model"], models["truth"], args.tolerance, args.max_rotation_deg)
    except ValueError as exc:
        print(f"benchmarks placement: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
