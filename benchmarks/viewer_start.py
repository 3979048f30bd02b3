"""How long nerfstudio's viewer takes to start on a trained run, as ``ns-viewer --load-config`` starts it.

    python -m benchmarks.viewer_start RUN/config.yml [--port 7100]     # one JSON line, then it exits

``ns-viewer`` prints nothing once it is ready and never exits, so this module does what it does, in its order, and
times each part: the pipeline and checkpoint loaded (``eval_setup``), the viser server up (``Viewer``), the scene
initialised (``init_scene``: the training cameras' frustums with their thumbnails, at most
``--viewer.max-num-display-images`` of them, and the panels), the first scene update; then it stops the server. The
scale benchmark (benchmarks/scale.py) runs it in its own process, so the peak memory is the viewer's.
"""

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from threading import Lock


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.viewer_start", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a trained run's config.yml")
    parser.add_argument("--port", type=int, default=0, help="the viewer's port (0: a free one, as ns-viewer picks it)")
    args = parser.parse_args(list(argv) if argv is not None else sys.argv[1:])
    config_path = Path(args.config)
    if not config_path.is_file():
        print(f"benchmarks.viewer_start: {config_path} is not a file (a trained run's config.yml)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    from nerfstudio.utils.eval_utils import eval_setup
    from nerfstudio.viewer.viewer import Viewer

    config, pipeline, _, step = eval_setup(config_path, eval_num_rays_per_chunk=None, test_mode="test")
    loaded = time.perf_counter()
    config.viewer.websocket_port = args.port or None  # None: nerfstudio's Viewer takes a free port
    viewer = Viewer(
        config.viewer,
        log_filename=config.get_base_dir() / config.viewer.relative_log_filename,
        datapath=pipeline.datamanager.get_datapath(),
        pipeline=pipeline,
        share=False,
        train_lock=Lock(),
    )
    server = time.perf_counter()
    train, evaluation = pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset
    viewer.init_scene(train_dataset=train, train_state="completed", eval_dataset=evaluation)
    scene = time.perf_counter()
    viewer.update_scene(step=step)
    ready = time.perf_counter()
    viewer.viser_server.stop()
    print(
        json.dumps(
            {
                "viewer_load_s": round(loaded - t0, 2),
                "viewer_server_s": round(server - loaded, 2),
                "viewer_scene_s": round(scene - server, 2),
                "viewer_ready_s": round(ready - t0, 2),
                "viewer_cameras": len(train),
                "viewer_frustums": len(viewer.camera_handles),
            }
        ),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
