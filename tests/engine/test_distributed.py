"""Data-parallel training (willags_ns/engine/distributed.py, `--machine.num-devices N`) on CPU with gloo and 2 processes.

- the collectives (gradient averaging, densification statistics, latents, broadcast, agreement check, shared RNG) in
  a bare 2-process gloo group;
- a tiny willags run launched through nerfstudio's own launcher (`nerfstudio.scripts.train.launch`, num_devices=2,
  device_type cpu), with densification in between: both ranks end with identical parameters, and one process that
  trains on the same image pairs with averaged gradients ends where they do;
- clear errors for settings data-parallel training does not support.
"""

import itertools
import socket
import threading
from functools import cached_property
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from willags_ns.engine.distributed import (
    DataParallelError,
    GradientAverager,
    ImageCachePrefetch,
    Placeholder,
    RankSyncedStrategy,
    all_reduce_strategy_state,
    apply_latent_rows,
    average_gradients,
    broadcast_module,
    check_parameters_agree,
    from_rank_zero,
    is_placeholder,
    latent_row,
    rank_images,
    same_rng,
    shard_image_cache,
    shard_train_images,
    share_train_latents,
    synced_strategy,
    validate_data_parallel,
    validate_train_images,
)
from willags_ns.engine.step_profile import read_step_profile

WORLD = 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gloo_worker(rank: int, port: int, fn) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=WORLD)
    try:
        fn(rank)
    finally:
        dist.destroy_process_group()


def _run_gloo(fn) -> None:
    """fn(rank) in each of WORLD spawned processes sharing a gloo group; an assertion in any fails the test."""
    mp.spawn(_gloo_worker, args=(_free_port(), fn), nprocs=WORLD, join=True)


# ---------------------------------------------------------------------------------------------------- collectives
def _collectives(rank: int) -> None:
    # gradients: averaged; a gradient one rank lacks counts as zero there; none anywhere stays None
    a, b, c = (torch.nn.Parameter(torch.zeros(3)) for _ in range(3))
    a.grad = torch.full((3,), float(rank + 1))  # 1 and 2 -> mean 1.5
    if rank == 1:
        b.grad = torch.tensor([4.0, -2.0, 0.0])  # only rank 1 -> half of it
    average_gradients([a, b, c], WORLD)
    assert torch.equal(a.grad, torch.full((3,), 1.5))
    assert torch.equal(b.grad, torch.tensor([2.0, -1.0, 0.0]))
    assert c.grad is None

    # densification statistics: grad2d and count summed, radii max
    state = {
        "grad2d": torch.tensor([1.0, 0.0]) * (rank + 1),
        "count": torch.tensor([1.0, float(rank)]),
        "radii": torch.tensor([0.1, 0.5]) if rank == 0 else torch.tensor([0.3, 0.2]),
        "scene_scale": 1.0,
    }
    all_reduce_strategy_state(state)
    assert torch.equal(state["grad2d"], torch.tensor([3.0, 0.0]))
    assert torch.equal(state["count"], torch.tensor([2.0, 1.0]))
    assert torch.equal(state["radii"], torch.tensor([0.3, 0.5]))

    # latents: each rank's image row reaches every rank
    latents, seen = torch.zeros(4, 2), torch.zeros(4, dtype=torch.bool)
    idx = 2 * rank + 1  # rank 0 saw image 1, rank 1 image 3
    latents[idx], seen[idx] = torch.tensor([float(idx), -1.0]), True
    share_train_latents(latents, seen, idx)
    assert seen.tolist() == [False, True, False, True]
    assert torch.equal(latents[1], torch.tensor([1.0, -1.0])) and torch.equal(latents[3], torch.tensor([3.0, -1.0]))

    # broadcast: rank 0's initialisation everywhere (nerfstudio seeds every rank differently)
    torch.manual_seed(100 + rank)
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    net[1].running_mean.fill_(rank)
    net.register_buffer("flag", torch.tensor([rank == 0, rank == 1]))
    # a non-contiguous buffer (a column-major solve result, say): NCCL refuses non-contiguous tensors (gloo takes
    # them), so the broadcast here refuses them as NCCL does
    net.register_buffer("cols", torch.arange(6.0).reshape(2, 3).t() * (rank + 1))
    assert not net.cols.is_contiguous()
    import willags_ns.engine.distributed as wd

    gloo_broadcast = wd.dist.broadcast

    def nccl_like_broadcast(tensor, src, *args, **kwargs):
        if not tensor.is_contiguous():
            raise ValueError("Tensors must be contiguous")
        return gloo_broadcast(tensor, src, *args, **kwargs)

    wd.dist.broadcast = nccl_like_broadcast
    try:
        broadcast_module(net)
    finally:
        wd.dist.broadcast = gloo_broadcast
    check_parameters_agree(dict(net.named_parameters()), "after the broadcast")
    assert net[1].running_mean.eq(0).all() and net.flag.tolist() == [True, False]
    assert torch.equal(net.cols, torch.arange(6.0).reshape(2, 3).t())

    # ranks that built different models are named, not left to hang or silently diverge
    other = torch.nn.Linear(3, 4 + rank)
    with pytest.raises(DataParallelError, match="built different models"):
        broadcast_module(other)

    # a divergence is reported with the tensor's name
    means = torch.ones(5, 3)
    if rank == 1:
        means[2, 0] = 1.5
    with pytest.raises(DataParallelError, match="'means'.*rank"):
        check_parameters_agree({"quats": torch.ones(5, 4), "means": means}, "in the test")

    # work done once, on rank 0, its result on every rank; its failure raised everywhere
    calls = []
    value, here = from_rank_zero(lambda: calls.append(rank) or {"settings": {"use_mask": False}})
    assert value == {"settings": {"use_mask": False}} and here == (rank == 0) and calls == ([0] if rank == 0 else [])

    def fails():
        raise ValueError("no scene")

    with pytest.raises(ValueError if rank == 0 else DataParallelError, match="no scene"):
        from_rank_zero(fails)

    # shared RNG for the refinement; each rank's own stream is untouched by it
    torch.manual_seed(7 + rank)
    expected_own = torch.randn(4, generator=torch.Generator().manual_seed(7 + rank))
    with same_rng(1234, "cpu"):
        drawn = torch.randn(6)
    assert torch.equal(torch.randn(4), expected_own)
    everyone = [torch.empty(6) for _ in range(WORLD)]
    dist.all_gather(everyone, drawn)
    assert torch.equal(everyone[0], everyone[1])


def _toy_training(rank: int, average) -> tuple[list[torch.Tensor], list[list[bool]]]:
    """Six Adam steps of three parameters on this rank's own data, gradients averaged by `average(params)`; at
    step 3 the first parameter grows (as densification replaces the Gaussians: a new Parameter of another size); the
    second is unused at step 2 on rank 1 and at step 4 everywhere, the third used on rank 1 only. Returns the final
    values and, per step, which parameters had a gradient after averaging."""
    gen = torch.Generator().manual_seed(0)  # the same initial values on every rank
    params = [torch.nn.Parameter(torch.randn(40, 3, generator=gen)) for _ in range(1)]
    params += [torch.nn.Parameter(torch.randn(7, generator=gen)), torch.nn.Parameter(torch.randn(4, 2, generator=gen))]
    opt = torch.optim.Adam(params, lr=0.05)
    has_grad = []
    for step in range(6):
        if step == 3:
            params[0] = torch.nn.Parameter(torch.cat([params[0].detach(), params[0].detach()[:9] * 0.5]))
            opt = torch.optim.Adam(params, lr=0.05)
        opt.zero_grad()
        data = torch.Generator().manual_seed(100 * rank + step)
        loss = (params[0] * torch.randn(params[0].shape, generator=data)).sum().square()
        if not ((step == 2 and rank == 1) or step == 4):
            loss = loss + (params[1] * torch.randn(7, generator=data)).sin().sum()
        if rank == 1:
            loss = loss + params[2].square().sum()
        loss.backward()
        average(params)
        has_grad.append([p.grad is not None for p in params])
        opt.step()
    return [p.detach().clone() for p in params], has_grad


def _averagers(rank: int) -> None:
    # the buffered averager gives the reference implementation's averages, step after step (sizes changing)
    reference = _toy_training(rank, lambda ps: average_gradients(ps, WORLD))
    averager = GradientAverager(WORLD)
    buffered = _toy_training(rank, lambda ps: averager.average(ps))
    assert reference[1] == buffered[1]
    assert reference[1][4] == [True, False, True]  # no rank used the second: no gradient, as in one process
    for a, b in zip(reference[0], buffered[0], strict=True):
        assert torch.equal(a, b)
    assert averager.bytes_reduced == 4 * (3 + 49 * 3 + 7 + 8)
    # a gradient this rank lacks but another has is read back once; none lacking: no read-back
    a, b = torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(2))
    a.grad = torch.full((3,), float(rank + 1))
    if rank == 1:
        b.grad = torch.tensor([4.0, -2.0])
    averager.average([a, b])
    assert torch.equal(a.grad, torch.full((3,), 1.5)) and torch.equal(b.grad, torch.tensor([2.0, -1.0]))
    assert averager.host_reads == (1 if rank == 0 else 0)

    # gradient accumulation (a group stepped every other step): the backward adds into the last call's averaged view
    c = torch.nn.Parameter(torch.zeros(3))
    c.grad = torch.full((3,), float(rank))
    averager.average([a, c])  # c: mean 0.5
    c.grad.add_(float(rank + 2))  # 0.5 + 2 | 0.5 + 3
    averager.average([c])
    assert torch.equal(c.grad, torch.full((3,), 3.0))

    # extra rows ride along: rank r's row arrives exactly at row r of every rank
    mine = torch.tensor([float(rank), 1.0 / 3.0 + rank, -7.25])
    rows = averager.average([a], mine, 3)
    assert rows is not None and rows.shape == (WORLD, 3)
    everyone = [torch.empty(3) for _ in range(WORLD)]
    dist.all_gather(everyone, mine)
    assert torch.equal(rows, torch.stack(everyone))

    # the training images' latents shared through the rows, without reading anything back
    latents, seen = torch.zeros(4, 2), torch.zeros(4, dtype=torch.bool)
    idx = 2 * rank + 1  # rank 0 saw image 1, rank 1 image 3
    latents[idx], seen[idx] = torch.tensor([float(idx), -1.0]), True
    rows = averager.average([a], latent_row(latents, seen, idx, torch.device("cpu")), 3)
    apply_latent_rows(latents, seen, rows)
    assert seen.tolist() == [False, True, False, True]
    assert torch.equal(latents[1], torch.tensor([1.0, -1.0])) and torch.equal(latents[3], torch.tensor([3.0, -1.0]))


def test_collectives_over_two_gloo_ranks():
    _run_gloo(_collectives)


def test_buffered_averaging_equals_the_reference_over_two_gloo_ranks():
    _run_gloo(_averagers)


def test_latent_rows_name_their_image_or_nothing():
    latents = torch.arange(8, dtype=torch.float32).view(4, 2)
    seen = torch.tensor([True, False, True, True])
    assert latent_row(latents, seen, 1, torch.device("cpu")).tolist() == [-1.0, -1.0, -1.0]  # not seen yet
    assert latent_row(latents, seen, 9, torch.device("cpu")).tolist() == [-1.0, -1.0, -1.0]  # no such image
    assert latent_row(latents, seen, 2, torch.device("cpu")).tolist() == [2.0, 4.0, 5.0]
    target, known = torch.zeros(4, 2), torch.zeros(4, dtype=torch.bool)
    apply_latent_rows(target, known, torch.tensor([[2.0, 4.0, 5.0], [-1.0, -1.0, -1.0], [0.0, -0.5, 7.0]]))
    assert known.tolist() == [True, False, True, False]
    assert target.tolist() == [[-0.5, 7.0], [0.0, 0.0], [4.0, 5.0], [0.0, 0.0]]


def test_image_cache_holds_only_the_rank_s_own_images():
    decoded = []

    class Dataset:
        cameras = SimpleNamespace(
            height=torch.tensor([4, 5, 6]), width=torch.tensor([7, 8, 9]), distortion_params=torch.zeros(3, 6)
        )

        def get_data(self, image_idx, image_type="float32"):
            decoded.append(image_idx)
            return {"image_idx": image_idx, "image": torch.ones(4 + image_idx, 7 + image_idx, 3)}

    dm = SimpleNamespace(train_dataset=Dataset())
    shard_image_cache(dm, 1, 2)
    own, other = dm.train_dataset.get_data(1), dm.train_dataset.get_data(2, image_type="uint8")
    assert decoded == [1] and not is_placeholder(own["image"])
    assert is_placeholder(other["image"]) and other["image"].shape == (6, 9, 3) and other["image"].dtype == torch.uint8
    # past 500 training images nerfstudio pins a host cache image by image; a broadcast tensor cannot be pinned, so
    # the placeholder's pinning returns it unchanged (no step of this rank copies it to its device)
    assert other["image"].pin_memory() is other["image"] and is_placeholder(other["image"].pin_memory())
    Dataset.cameras.distortion_params[0, 0] = 0.1  # undistortion needs a real array
    distorted = dm.train_dataset.get_data(0)["image"]
    assert distorted.shape == (4, 7, 3) and distorted.is_contiguous() and decoded == [1]
    dm.cached_train = []
    with pytest.raises(DataParallelError, match="cached before"):
        shard_image_cache(dm, 0, 2)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (pinned host memory)")
def test_a_host_cache_past_500_images_pins_its_own_images_and_keeps_the_placeholders():
    """nerfstudio pins each cached image when the cache stays on the host: a broadcast tensor cannot be pinned, the
    placeholder passes through unpinned, a rank's own image is pinned."""
    broadcast = torch.zeros((1, 1, 3), dtype=torch.uint8).expand(6, 9, 3)
    with pytest.raises(RuntimeError, match="more than one element"):
        broadcast.pin_memory()
    placeholder = broadcast.as_subclass(Placeholder)
    assert placeholder.pin_memory() is placeholder and is_placeholder(placeholder)
    assert torch.ones((6, 9, 3), dtype=torch.uint8).pin_memory().is_pinned()


def test_image_cache_prefetch_caches_once_in_its_thread_and_raises_its_error():
    """The cache is built once, in the background thread, and the pipeline's later reads get that same cache; a
    failure while caching (an unreadable photo) is raised where the pipeline waits for it."""
    threads = []

    class Datamanager:
        @cached_property
        def cached_train(self):
            threads.append(threading.current_thread().name)
            return [{"image_idx": 0}]

    dm = Datamanager()
    prefetch = ImageCachePrefetch(dm, "cpu")
    prefetch.wait()
    first = dm.cached_train
    assert threads == ["willags-image-cache"] and dm.cached_train is first and first == [{"image_idx": 0}]

    class Unreadable:
        @cached_property
        def cached_train(self):
            raise OSError("cannot identify image file 'frame_00003.jpg'")

    prefetch = ImageCachePrefetch(Unreadable(), "cpu")
    with pytest.raises(OSError, match="frame_00003.jpg"):
        prefetch.wait()


# ---------------------------------------------------------------------------------------------------- pure parts
def test_each_rank_gets_its_own_images_every_epoch():
    order = [5, 2, 7, 0, 3, 6, 1, 4]
    assert rank_images(order, 0, 2) == [2, 0, 6, 4] and rank_images(order, 1, 2) == [5, 7, 3, 1]
    epochs = iter([[3, 0, 2, 1, 4], [1, 4, 0, 3, 2], [4, 3, 2, 1, 0]])

    class Datamanager:  # nerfstudio's FullImageDatamanager: same seeded shuffles on every rank
        def __init__(self):
            self.train_unseen_cameras = next(epochs)

        def sample_train_cameras(self):
            return next(epochs)

    dm = Datamanager()
    shard_train_images(dm, 1, 2)
    assert dm.train_unseen_cameras == [3, 1]
    assert dm.sample_train_cameras() == [1, 3]
    dm0 = SimpleNamespace(train_unseen_cameras=[0, 1, 2], sample_train_cameras=lambda: [2, 1, 0])
    shard_train_images(dm0, 0, 1)  # one process: untouched
    assert dm0.train_unseen_cameras == [0, 1, 2] and dm0.sample_train_cameras() == [2, 1, 0]


def test_unsupported_settings_are_named():
    dm = SimpleNamespace(train_cameras_sampling_strategy="random")
    validate_data_parallel(1, "cpu", dm)  # one process: nothing to check
    with pytest.raises(DataParallelError, match="train-cameras-sampling-strategy fps"):
        validate_data_parallel(2, "cpu", SimpleNamespace(train_cameras_sampling_strategy="fps"))
    with pytest.raises(DataParallelError, match="full-image datamanager"):
        validate_data_parallel(2, "cpu", SimpleNamespace())
    with pytest.raises(DataParallelError, match="not mps"):
        validate_data_parallel(2, "mps", dm)
    with pytest.raises(DataParallelError, match="--machine.num-devices 2"):
        validate_data_parallel(2, "cpu", dm)  # no process group: not launched by nerfstudio's launcher
    validate_train_images(3, 2)
    with pytest.raises(DataParallelError, match="at least 4 training images"):
        validate_train_images(3, 4)


def test_synced_strategy_keeps_the_settings():
    from gsplat.strategy import DefaultStrategy

    base = DefaultStrategy(refine_every=7, grow_grad2d=0.123, refine_start_iter=3)
    s = synced_strategy(base, refine_seed=11, world_size=2)
    assert isinstance(s, RankSyncedStrategy) and isinstance(s, DefaultStrategy)
    assert (s.refine_every, s.grow_grad2d, s.refine_start_iter, s.refine_seed, s.world_size) == (7, 0.123, 3, 11, 2)
    assert s.grows_as is None  # gsplat's own growth


def test_synced_strategy_keeps_the_budget_on_the_growth():
    """A DefaultStrategy with a budget (splats/splitclone.py) synchronised over ranks grows within its budget, on
    the statistics as they are after the all-reduce (here one rank: as they are)."""
    from willags_ns.splats.splitclone import BudgetedDefaultStrategy

    base = BudgetedDefaultStrategy(grow_grad2d=0.001, cap_max=5)
    s = synced_strategy(base, refine_seed=3, world_size=1)
    assert s.grows_as is base and synced_strategy(s, refine_seed=3, world_size=1).grows_as is base
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.randn(4, 3)),
            "scales": torch.nn.Parameter(torch.full((4, 3), -5.0)),
            "quats": torch.nn.Parameter(torch.nn.functional.normalize(torch.randn(4, 4), dim=-1)),
            "opacities": torch.nn.Parameter(torch.zeros(4)),
        }
    )
    optimizers = {k: torch.optim.Adam([params[k]], lr=1e-3) for k in params}
    state = s.initialize_state(scene_scale=1.0)
    state.update(grad2d=torch.tensor([0.5, 0.4, 0.3, 0.2]), count=torch.ones(4), radii=torch.zeros(4))
    s._grow_gs(params, optimizers, state, step=600)
    assert params["means"].shape[0] == 5  # four eligible, room for one
    # the synced strategy's settings as they are now (the time budget refits them after the strategy is synced)
    # decide the growth, the budget its own: only 0.5 passes a threshold raised to 0.45
    s = synced_strategy(BudgetedDefaultStrategy(grow_grad2d=0.001, cap_max=10), refine_seed=3, world_size=1)
    s.grow_grad2d = 0.45
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach()[:4].clone()) for k, v in params.items()})
    optimizers = {k: torch.optim.Adam([params[k]], lr=1e-3) for k in params}
    state = s.initialize_state(scene_scale=1.0)
    state.update(grad2d=torch.tensor([0.5, 0.4, 0.3, 0.2]), count=torch.ones(4), radii=torch.zeros(4))
    s._grow_gs(params, optimizers, state, step=600)
    assert params["means"].shape[0] == 5


def test_mcmc_densification_is_seeded_alike_on_every_rank():
    """MCMC's moves (relocation, growth, position noise) need no statistics from the other ranks: every rank holds
    the same Gaussians, and synced_strategy seeds each step's draws alike, so two ranks move them identically."""
    from tests.splats.test_mcmc import _params
    from willags_ns.splats.mcmc import McmcDensification

    base = McmcDensification(cap_max=150, refine_start_iter=0, refine_stop_iter=100, refine_every=5)
    synced = synced_strategy(base, refine_seed=1234, world_size=2)
    assert isinstance(synced, McmcDensification) and synced.seed == 1234 and base.seed is None
    assert (synced.cap_max, synced.refine_every) == (150, 5)
    ranks = [_params(n=100, seed=0) for _ in range(2)]
    for step in range(1, 30):
        for params, optimizers in ranks:
            synced.step_post_backward(params, optimizers, {}, step, {}, lr=1e-3)
    (p0, _), (p1, _) = ranks
    assert len(p0["means"]) > 100
    for k in p0:
        assert torch.equal(p0[k], p1[k]), k


def test_willags_pipeline_refuses_several_devices_without_a_process_group():
    from willags_ns import method_configs

    config = method_configs.willags_config()
    with pytest.raises(DataParallelError, match="ns-train willags --machine.num-devices 2"):
        config.pipeline.setup(device="cpu", test_mode="val", world_size=2, local_rank=0)


# ---------------------------------------------------------------------------------------------------- training
STEPS = 14
"""Steps of the tiny run: refinements at steps 6, 9 and 12 (refine_every 3; after the opacity reset of step 0 gsplat
waits one epoch, 6 images / 2 ranks = 3 steps, + refine_every)."""


def _tiny_config(tmp_path: Path, scene: Path):
    """test_reliability's tiny in-process config, densifying hard in a few steps."""
    from tests.test_reliability import _tiny_config as reliability_config

    config = reliability_config(tmp_path, scene, steps=STEPS, refine_every=3)
    config.experiment_name = "ddp"
    config.pipeline.check_photo_content = False
    m = config.pipeline.model
    m.warmup_length = 2
    m.reset_alpha_every = 100
    m.densification = "splatfacto"  # its statistics the ranks all-reduce (MCMC's draws: below)
    m.densify_grad_thresh = 2e-5  # grow many Gaussians (split: random offsets) in a few steps
    m.background_color = "black"  # "random" draws per rank; the single-process reference must draw the same
    m.mask.warmup_steps = 4
    m.mask.vgg_weights = "seeded"
    config.pipeline.data_parallel.step_profile = True
    return config


@pytest.fixture(scope="module")
def launched_run(tmp_path_factory):
    """Launch a tiny willags run on 2 CPU ranks through nerfstudio's launcher; (config, [rank0 record, rank1])."""
    from nerfstudio.scripts.train import launch

    from tests._distributed_launch import record_path, train_and_record
    from willags_ns.data.synthetic import SyntheticSceneConfig, ensure_default_scene

    tmp = tmp_path_factory.mktemp("ddp")
    scene_cfg = SyntheticSceneConfig(num_train=6, num_test=1, width=32, height=24, num_points=400, supersample=1)
    scene = ensure_default_scene(scene_cfg, root=tmp / "scenes")
    config = _tiny_config(tmp, scene)
    config.set_timestamp()
    config.save_config()
    launch(main_func=train_and_record, num_devices_per_machine=WORLD, device_type="cpu", config=config)
    records = [torch.load(record_path(config, r), weights_only=False) for r in range(WORLD)]
    profile = read_step_profile(Path(config.get_base_dir()))  # read now: the single-process reference writes rank 0's
    for r, (meta, rows) in profile.items():
        records[r]["profile"] = (meta, rows)
    return config, records


@pytest.mark.slow
def test_launch_trains_on_two_ranks_with_their_own_images(launched_run):
    config, records = launched_run
    for rec in records:
        assert rec["wrapped"] == "WillagsModel", "the model must not be wrapped in DistributedDataParallel"
        assert rec["strategy"] == "RankSyncedStrategy"
        assert len(rec["images"]) == STEPS
    imgs0, imgs1 = records[0]["images"], records[1]["images"]
    assert all(i % 2 == 0 for i in imgs0) and all(i % 2 == 1 for i in imgs1), (imgs0, imgs1)
    assert set(imgs0) | set(imgs1) == set(range(6))
    assert records[0]["decoded"] == [0, 2, 4] and records[1]["decoded"] == [1, 3, 5]  # the image cache is sharded
    assert records[0]["refine_seed"] == records[1]["refine_seed"]
    assert records[0]["pause_refine_after_reset"] == 3 + 3  # one epoch of each rank's 3 images + refine_every
    counts, n0 = records[0]["num_points"], records[0]["initial"]["gauss_params.means"].shape[0]
    assert counts[5] == n0 and counts[6] != n0, f"no refinement at step 6: {counts} (from {n0})"
    assert counts == records[1]["num_points"]
    ckpts = list((Path(config.get_base_dir()) / "nerfstudio_models").glob("*.ckpt"))
    assert len(ckpts) == 1  # rank 0 alone writes checkpoints
    saved = torch.load(ckpts[0], map_location="cpu", weights_only=False)["pipeline"]
    assert not any(k.startswith("_model.module.") for k in saved)  # loads in a single process as usual
    torch.testing.assert_close(saved["_model.gauss_params.means"], records[0]["final"]["gauss_params.means"])


@pytest.mark.slow
def test_step_profile_of_each_rank(launched_run):
    """Each rank writes one row per step: its image, the spans in order, the bytes of the all-reduce (every gradient,
    the presence flags and one latent row per rank: nothing is read back on the host); and its start-up phases."""
    config, records = launched_run
    for rank, rec in enumerate(records):
        meta, rows = rec["profile"]
        assert meta["rank"] == rank and meta["world_size"] == WORLD and meta["reduction"] == "buffer"
        phases = meta["phases"]
        order = ["pipeline_init", "data_parsed", "model_built", "data_parallel_ready", "images_cached", "first_step"]
        order += ["train_end"]
        assert all(phases[a] <= phases[b] for a, b in itertools.pairwise(order)), phases
        assert [row["step"] for row in rows] == list(range(STEPS))
        assert [row["image"] for row in rows] == rec["images"]
        for row in rows:
            assert row["host_reads"] == 0
            assert row["gaussians"] > 0 and row["pixels"] > 0
            spans = [
                row[f"h_{k}"] for k in ("forward", "backward", "pack", "collective", "unpack", "optimizer", "callbacks")
            ]
            assert all(v >= 0 for v in spans)
            assert row["h_iteration"] >= sum(spans) - 1e-3
        n_params = sum(v.numel() for k, v in rec["final"].items() if k.startswith("gauss_params."))
        assert rows[-1]["bytes"] > 4 * n_params  # the Gaussians' gradients of the last step, at least


@pytest.mark.slow
def test_ranks_end_with_identical_parameters(launched_run):
    _, (r0, r1) = launched_run
    for state in ("initial", "final"):
        assert r0[state].keys() == r1[state].keys()
        for k in r0[state]:
            assert torch.equal(r0[state][k], r1[state][k]), f"{state} {k} differs between the ranks"


@pytest.mark.slow
def test_two_machines_of_one_device_train_together(tmp_path):
    """Two launches started separately, as two machines of one device each (`--machine.num-machines 2
    --machine.machine-rank 0|1 --machine.dist-url tcp://127.0.0.1:PORT`): global ranks 0 and 1 train on the even and
    the odd images, refine together (at step 6) and end with the same parameters, bit for bit. With the VAE latent:
    each rank encodes only its own images, and both end knowing the latents of all of them."""
    import os
    import subprocess
    import sys

    from tests._distributed_launch import record_path
    from willags_ns.data.synthetic import SyntheticSceneConfig, ensure_default_scene

    scene_cfg = SyntheticSceneConfig(num_train=6, num_test=1, width=32, height=24, num_points=400, supersample=1)
    config = _tiny_config(tmp_path, ensure_default_scene(scene_cfg, root=tmp_path / "scenes"))
    config.max_num_iterations = 8
    config.pipeline.data_parallel.step_profile = False
    config.pipeline.model.latent.kind = "vae"
    config.machine.num_devices, config.machine.num_machines = 1, 2
    config.machine.dist_url = f"tcp://127.0.0.1:{_free_port()}"
    config.set_timestamp()
    config.save_config()
    yml = Path(config.get_base_dir()) / "config.yml"
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from tests._distributed_launch import launch_machine; launch_machine(sys.argv[1], int(sys.argv[2]))"
    machines = [
        subprocess.Popen(
            [sys.executable, "-c", code, str(yml), str(r)],
            cwd=repo,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for r in (1, 0)  # the second machine may start first: it waits for the first at the rendezvous
    ]
    logs = [m.communicate(timeout=600)[0] for m in machines]
    assert all(m.returncode == 0 for m in machines), "\n".join(log[-3000:] for log in logs)
    r0, r1 = (torch.load(record_path(config, r), weights_only=False) for r in range(2))
    assert all(i % 2 == 0 for i in r0["images"]) and all(i % 2 == 1 for i in r1["images"])
    assert len(r0["images"]) == len(r1["images"]) == 8
    assert r0["num_points"] == r1["num_points"] and r0["num_points"][6] != r0["num_points"][5]  # refined at step 6
    for state in ("initial", "final"):
        for k in r0[state]:
            assert torch.equal(r0[state][k], r1[state][k]), f"{state} {k} differs between the machines"
    assert r0["final"]["train_latent_seen"].all()  # the appearances of every training image, on both machines


def _reference(config, records):
    """One process, the same initial state, each step the two ranks' images: forward + backward of each image (its
    densification statistics recorded after its own backward, as on its rank), gradients divided by 2, one
    optimiser step, then nerfstudio's after-step callbacks (refinement with the same seed). Returns the model."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    torch.manual_seed(0)
    config.pipeline.checkpoint_on_interrupt = False  # no SIGINT handler in the test process
    config.pipeline.data_parallel.step_profile = False  # the reference drives the optimiser step itself
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline, model, optimizers = trainer.pipeline, trainer.pipeline.model, trainer.optimizers
    with torch.no_grad():
        for k, v in records[0]["initial"].items():
            model.state_dict()[k].copy_(v)
    from gsplat.strategy import DefaultStrategy

    assert isinstance(model.strategy, DefaultStrategy) and not isinstance(model.strategy, RankSyncedStrategy), (
        "one process must keep its own strategy (gsplat's, with its budget)"
    )
    assert not hasattr(optimizers.optimizer_scaler_step_some, "willags_averages_gradients")
    strategy = synced_strategy(model.strategy, records[0]["refine_seed"], world_size=1)  # the ranks' seeded splits
    strategy.pause_refine_after_reset = records[0]["pause_refine_after_reset"]  # the ranks' schedule
    model.strategy = strategy
    callbacks = trainer.callbacks  # the model's (step, densification, teacher EMA) and the pipeline's
    groups = list(optimizers.parameters.keys())
    update_state = strategy._update_state
    pipeline.train()
    for step in range(STEPS):
        for cb in callbacks:
            cb.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        optimizers.zero_grad_all()
        for rec in records:
            pipeline.datamanager.train_unseen_cameras = [rec["images"][step]]
            _, loss_dict, _ = pipeline.get_train_loss_dict(step)
            sum(loss_dict.values()).backward()
            update_state(model.gauss_params, model.strategy_state, model.info, packed=False)
            model.end_step(step)
        for opt in optimizers.optimizers.values():
            for group in opt.param_groups:
                for p in group["params"]:
                    if p.grad is not None:
                        p.grad.div_(len(records))
        optimizers.optimizer_scaler_step_some(trainer.grad_scaler, groups)
        optimizers.scheduler_step_all(step)
        strategy._update_state = lambda *a, **k: None  # already recorded per image above
        for cb in callbacks:
            cb.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        del strategy._update_state
    return model


@pytest.mark.slow
def test_two_ranks_equal_one_process_on_the_same_image_pairs(launched_run):
    config, records = launched_run
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the ranks' reductions ran on one thread each
    try:
        model = _reference(config, records)
    finally:
        torch.set_num_threads(threads)
    final = records[0]["final"]
    ref = model.state_dict()
    assert ref["gauss_params.means"].shape == final["gauss_params.means"].shape, "densification decided differently"
    assert ref["gauss_params.means"].shape[0] != records[0]["initial"]["gauss_params.means"].shape[0]
    for k, v in final.items():
        torch.testing.assert_close(ref[k], v, rtol=1e-4, atol=1e-6, msg=lambda m, k=k: f"{k}: {m}")
