"""Small synthetic scenes written to disk for the tests that train on one (willags_ns/data/synthetic.py)."""

from pathlib import Path

from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene

SMALL = dict(num_train=20, num_test=2, width=96, height=72, num_points=3000, supersample=1)
"""A scene that trains in seconds on the CPU and still has enough views for the inspector."""


def small_scene(path: Path, appearance: float, transients: float, **size) -> Path:
    """Write a SMALL scene (``size`` overrides its fields) with ``appearance`` strength and ``transients`` fraction
    to ``path``; returns the scene directory."""
    cfg = SyntheticSceneConfig(appearance_strength=appearance, transient_fraction=transients, **{**SMALL, **size})
    return write_scene(make_scene(cfg), path)


def sfm_model_stub(scene: Path, points: bytes = b"points") -> Path:
    """A stand-in COLMAP model in ``scene/colmap/sparse/0`` (benchmarks/collections.py's MODEL_FILES, each holding
    its own name, points3D.bin ``points``) for the tests of what hashes a scene's model; returns ``scene``."""
    from benchmarks.collections import MODEL_FILES

    sparse = scene / "colmap" / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    for name in MODEL_FILES:
        (sparse / name).write_bytes(points if name == "points3D.bin" else name.encode())
    return scene
