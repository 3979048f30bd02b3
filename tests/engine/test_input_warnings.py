"""The input checks' warnings at scale: a few are printed one by one, many as a summary (counts per kind, a few photos
each) naming the run folder's list of every one (willags_ns/engine/checks.py, the pipeline)."""

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from tests._scenes import small_scene
from willags_ns.data.consistency import FOREIGN_PHOTO
from willags_ns.data.dataparser import InputWarning
from willags_ns.engine.checks import (
    DUPLICATE_PHOTO,
    INPUT_WARNINGS_FILE,
    MAX_LISTED_WARNINGS,
    report_warnings,
    summarise_warnings,
)


def _warnings(kind: str, n: int, start: int = 0) -> list[InputWarning]:
    return [
        InputWarning(f"photo {i:04d}.jpg: something about it", kind, f"{i:04d}.jpg") for i in range(start, start + n)
    ]


def test_a_summary_counts_each_kind_and_names_a_few_photos_of_each():
    found = _warnings(DUPLICATE_PHOTO, 938) + _warnings(FOREIGN_PHOTO, 2, start=2000) + ["a plain warning"]
    text = summarise_warnings(found, "there.txt")
    lines = text.splitlines()
    assert len(lines) == 4  # the count and where the list is, then one line per kind
    assert lines[0] == "941 warnings about the input (the full list: there.txt):"
    assert lines[1] == f"  938 {DUPLICATE_PHOTO}, e.g. 0000.jpg; 0001.jpg; 0002.jpg, and 935 more"
    assert lines[2] == f"  2 {FOREIGN_PHOTO}, e.g. 2000.jpg; 2001.jpg"
    assert lines[3] == "  1 other warnings, e.g. a plain warning"


def test_a_few_warnings_are_printed_one_by_one_and_many_as_one_summary():
    few = _warnings(DUPLICATE_PHOTO, MAX_LISTED_WARNINGS)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert report_warnings(few, "there.txt") is False
    assert [str(w.message) for w in caught] == few
    many = _warnings(DUPLICATE_PHOTO, MAX_LISTED_WARNINGS + 1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert report_warnings(many, "there.txt") is True
    assert len(caught) == 1 and str(caught[0].message) == summarise_warnings(many, "there.txt")


@pytest.mark.slow
def test_many_duplicates_print_a_summary_and_the_run_folder_lists_every_one(tmp_path, capsys):
    from tests.test_train import train_recording
    from willags_ns.method_configs import willags_3dgs_config

    scene = small_scene(tmp_path / "scene", 0.0, 0.0, num_train=16, width=32, height=24, num_points=300)
    train = [scene / f for f in json.loads((scene / "transforms.json").read_text())["train_filenames"]]
    copies = train[1 : MAX_LISTED_WARNINGS + 3]  # one more than are listed one by one
    for p in copies:
        shutil.copy(train[0], p)
    config = willags_3dgs_config()
    config.machine.device_type = "cpu"
    config.pipeline.datamanager.data = scene
    config.max_num_iterations = config.steps_per_save = 1
    config.vis, config.output_dir, config.timestamp = "tensorboard", tmp_path / "out", "t"
    config.set_timestamp()
    config.save_config()
    with pytest.warns(UserWarning) as record:
        trainer, losses = train_recording(config)
    assert len(losses) == 1 and torch.isfinite(torch.tensor(losses[0][0]))
    texts = [
        str(w.message) for w in record if "byte-identical" in str(w.message) or "about the input" in str(w.message)
    ]
    assert len(texts) == 1 and texts[0].startswith(f"{len(copies)} warnings about the input"), texts
    printed = capsys.readouterr().out
    assert "are byte-identical files" not in printed  # no warning block per photo
    listed = Path(trainer.base_dir) / INPUT_WARNINGS_FILE
    assert f"willags: the {len(copies)} warnings about the input: {listed}" in printed.splitlines()
    lines = listed.read_text().splitlines()
    assert len(lines) == len(copies) and all("byte-identical" in line for line in lines)
    assert {line.split(" and ")[0] for line in lines} == {str(p) for p in copies}
