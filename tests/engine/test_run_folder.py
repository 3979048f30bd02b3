"""The run folder is made on every rank before nerfstudio writes into it (engine/trainer.make_run_folder)."""

import json
import threading

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs

from willags_ns.engine.trainer import make_run_folder


def _outputs() -> DataparserOutputs:
    cams = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=1.0, fy=1.0, cx=1.0, cy=1.0, width=2, height=2)
    return DataparserOutputs(image_filenames=[], cameras=cams, dataparser_transform=torch.eye(4)[:3])


def test_ranks_starting_together_all_write_the_transform_into_one_new_run_folder(tmp_path):
    run = tmp_path / "outputs" / "scene" / "willags" / "run"
    ranks, errors = 8, []
    barrier = threading.Barrier(ranks)

    def rank() -> None:
        try:
            barrier.wait()
            make_run_folder(run)
            _outputs().save_dataparser_transform(run / "dataparser_transforms.json")
        except Exception as e:  # noqa: BLE001 - collected and asserted below
            errors.append(e)

    threads = [threading.Thread(target=rank) for _ in range(ranks)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert (run / "dataparser_transforms.json").is_file()
    assert np.allclose(
        np.array(json.loads((run / "dataparser_transforms.json").read_text())["transform"]), np.eye(4)[:3]
    )


def test_an_existing_run_folder_is_kept_with_its_files(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yml").write_text("kept")
    make_run_folder(run)
    assert (run / "config.yml").read_text() == "kept"
