"""Test harness only (tests/engine/test_distributed.py): run nerfstudio's own multi-process launcher on a CPU-only machine
and record what each rank did.

nerfstudio 1.1.5's `_distributed_worker` asserts `torch.cuda.is_available()` and `num_devices <=
torch.cuda.device_count()` before it initialises the process group, even for `--machine.device-type cpu` (gloo).
Each worker imports this module while it unpickles `train_and_record` (its main_func), before
`_distributed_worker` runs; in a worker without CUDA, those two functions then answer "yes, 64 devices" to callers
in nerfstudio.scripts.train only (the launcher's asserts) and the truth to everyone else.
"""

import multiprocessing
import os
import sys
from pathlib import Path

import torch

_LAUNCHER = "nerfstudio.scripts.train"


def _from_launcher() -> bool:
    return sys._getframe(2).f_globals.get("__name__") == _LAUNCHER


def _fake_cuda_for_the_launcher() -> None:
    real_available, real_count = torch.cuda.is_available, torch.cuda.device_count

    def is_available() -> bool:
        return True if _from_launcher() else real_available()

    def device_count() -> int:
        return 64 if _from_launcher() else real_count()

    torch.cuda.is_available = is_available
    torch.cuda.device_count = device_count


# a spawned worker (parent_process() is not set yet while it unpickles its target)
if multiprocessing.current_process().name != "MainProcess" and not torch.cuda.is_available():
    _fake_cuda_for_the_launcher()


def record_path(config, rank: int) -> Path:
    return Path(config.get_base_dir()) / f"rank{rank}.pt"


def tensors(model) -> dict:
    """The model's state_dict tensors (not its `_extra_state`), cloned."""
    return {k: v.detach().clone() for k, v in model.state_dict().items() if torch.is_tensor(v)}


def train_and_record(local_rank: int, world_size: int, config, global_rank: int = 0) -> None:
    """nerfstudio's `train_loop` (seed + rank, Trainer setup, train), recording for the tests: rank 0's model
    state after setup, the refinement seed, each step's training image, the Gaussian count after each step, and the
    final model state (written to `record_path`)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed

    torch.set_num_threads(1)  # 2 ranks on a 2-core machine; also makes the CPU reductions reproducible
    windows = os.environ.get("WILLAGS_TEST_BUDGET_STEPS")  # "warm-up,window,replan": a time budget's, shortened
    if windows:
        from willags_ns.engine import time_budget

        time_budget.WARMUP_STEPS, time_budget.WINDOW_STEPS, time_budget.REPLAN_EVERY = map(int, windows.split(","))
    _set_random_seed(config.machine.seed + global_rank)
    trainer = config.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    pipeline, model = trainer.pipeline, trainer.pipeline.model
    record = {
        "initial": tensors(model),
        "refine_seed": getattr(model.strategy, "refine_seed", None),
        "pause_refine_after_reset": getattr(model.strategy, "pause_refine_after_reset", None),
        "strategy": type(model.strategy).__name__,
        "wrapped": type(pipeline._model).__name__,
        "images": [],
        "num_points": [],
    }
    get_loss = pipeline.get_train_loss_dict

    def recording_get_loss(step: int):
        out = get_loss(step)
        record["images"].append(pipeline._step_image_idx)
        return out

    pipeline.get_train_loss_dict = recording_get_loss
    trainer.callbacks.append(
        TrainingCallback(
            [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], lambda step: record["num_points"].append(model.num_points)
        )
    )
    trainer.train()
    record["final"] = tensors(model)
    from willags_ns.engine.distributed import is_placeholder

    record["decoded"] = [i for i, c in enumerate(pipeline.datamanager.cached_train) if not is_placeholder(c["image"])]
    torch.save(record, record_path(config, global_rank))


def launch_machine(config_yml: str, machine_rank: int) -> None:
    """One "machine" of a several-machine run, as `ns-train ... --machine.num-machines M --machine.machine-rank R
    --machine.dist-url URL` starts it (nerfstudio.scripts.train.main: the launcher with the config's machine
    settings), recording each rank as `train_and_record` does. `config_yml`: the run's config.yml, the same on every
    machine but for machine_rank."""
    import yaml
    from nerfstudio.scripts.train import launch

    config = yaml.load(Path(config_yml).read_text(), Loader=yaml.Loader)
    config.machine.machine_rank = machine_rank
    launch(
        main_func=train_and_record,
        num_devices_per_machine=config.machine.num_devices,
        num_machines=config.machine.num_machines,
        machine_rank=config.machine.machine_rank,
        dist_url=config.machine.dist_url,
        device_type=config.machine.device_type,
        config=config,
    )
