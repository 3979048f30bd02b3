"""Data-parallel training of the willags methods over several devices (`ns-train willags --machine.num-devices N`).

nerfstudio's launcher starts one process per device and initialises torch.distributed (NCCL for
`--machine.device-type cuda`, gloo otherwise); its VanillaPipeline would then wrap the model in
DistributedDataParallel. DDP fixes its gradient buckets when it is built, and densification replaces the
Gaussians' parameters every `refine_every` steps, so WillagsPipeline does not wrap the model. Instead:

- every rank holds all Gaussians and appearance networks; rank 0's initial state is broadcast to the others
  (`broadcast_module`), after checking that every rank built the same parameter set;
- each rank trains on its own share of the training images (`shard_train_images`: image i belongs to rank
  i mod N, shuffled per epoch), so one step sees N different images;
- after the backward pass and before the optimiser step, every gradient is summed over the ranks and divided by N
  (`average_gradients`): one step is the single-process step on the *mean* loss of the N images. Averaged, not
  summed: the learning rates keep their meaning (Adam is scale-invariant anyway) and an average of identical values
  is a no-op, so gradient accumulation stays correct;
- densification statistics (gsplat's DefaultStrategy state: grad2d and count summed, radii max) are all-reduced
  just before each refinement, so every rank takes the same densify / prune decisions, and the refinement runs
  under the same RNG state on every rank (`same_rng`, seeded from rank 0's draw + the step), so split Gaussians get
  the same random offsets everywhere (no broadcast of the Gaussians afterwards). `check_parameters_agree` then
  compares the Gaussians' signatures over the ranks and stops with an error should they ever differ;
- each step's latent of a training image (the per-image embedding row or the VAE mean recorded in
  `train_latents`) is shared with every rank (`share_train_latents`), so every rank's checkpoint and viewer know
  the appearances of all images.

Per rank and not shared: the EMA teacher (computed from identical student weights, so it stays identical), the VAE
forward of the rank's own image, the transient masks of the rank's images and their per-image visit counts (image i
always lives on the same rank, so its mask cadence is the single-process one).

Every function here is a no-op or a plain computation for world_size == 1; the single-process path never calls them.
"""

import itertools
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields
from typing import Any

import torch
import torch.distributed as dist
from gsplat.strategy import DefaultStrategy
from torch import Tensor, nn

AGREE_RTOL = 1e-5
"""Relative tolerance of `check_parameters_agree` on a tensor's sum / sum of |x|. Ranks apply identical updates
to identical values, so they agree exactly; the tolerance only keeps the check from tripping on a device whose
reductions round differently."""


class DataParallelError(ValueError):
    """A setting that data-parallel training (num_devices > 1) does not support, or ranks that disagree."""


def rank_and_world_size() -> tuple[int, int]:
    """(global rank, world size) of this process; (0, 1) without an initialised process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def comm_device() -> torch.device:
    """Where tensors must be for the process group's backend: NCCL moves CUDA tensors (of this rank's current
    device, which WillagsPipeline sets), gloo CPU tensors."""
    if dist.is_initialized() and dist.get_backend() == dist.Backend.NCCL:
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


# ---------------------------------------------------------------------------------------------------- checks
def validate_data_parallel(world_size: int, device: Any, datamanager_config: Any) -> None:
    """Stop with a clear message before anything is built when `world_size` > 1 cannot work: the settings first,
    then the process group nerfstudio's launcher should have set up."""
    if world_size <= 1:
        return
    strategy = getattr(datamanager_config, "train_cameras_sampling_strategy", None)
    if strategy is None:
        raise DataParallelError(
            "willags: several devices need nerfstudio's full-image datamanager (one image per step per device); "
            f"got {type(datamanager_config).__name__}"
        )
    if strategy != "random":
        raise DataParallelError(
            f"willags: --pipeline.datamanager.train-cameras-sampling-strategy {strategy} is not supported with "
            f"--machine.num-devices {world_size} (each device draws its own share of the images at random); use "
            "'random'"
        )
    dev = torch.device(str(device)) if device is not None else torch.device("cpu")
    if dev.type not in ("cuda", "cpu"):
        raise DataParallelError(
            f"willags: several devices are supported on cuda (NCCL) and cpu (gloo), not {dev.type}; use "
            "--machine.num-devices 1"
        )
    if not (dist.is_available() and dist.is_initialized()):
        raise DataParallelError(
            f"willags: world_size={world_size} but no torch.distributed process group is initialised; launch with "
            f"`ns-train willags --machine.num-devices {world_size}` (nerfstudio's launcher sets it up)"
        )
    if dist.get_world_size() != world_size:
        raise DataParallelError(
            f"willags: the pipeline got world_size={world_size} but the process group has {dist.get_world_size()} ranks"
        )
    backend = dist.get_backend()
    if (dev.type == "cuda" and backend != dist.Backend.NCCL) or (dev.type == "cpu" and backend != dist.Backend.GLOO):
        raise DataParallelError(
            f"willags: training on {dev.type} needs the {'nccl' if dev.type == 'cuda' else 'gloo'} backend, the "
            f"process group uses {backend} (set --machine.device-type to match the device)"
        )


def validate_train_images(num_images: int, world_size: int) -> None:
    """Every rank needs at least one training image of its own."""
    if world_size > 1 and num_images < world_size:
        raise DataParallelError(
            f"willags: {world_size} devices need at least {world_size} training images (one per device), the scene "
            f"has {num_images}; use --machine.num-devices {max(1, num_images)}"
        )


# ---------------------------------------------------------------------------------------------------- images
def rank_images(indices: Iterable[int], rank: int, world_size: int) -> list[int]:
    """The entries of `indices` that belong to `rank`: image i belongs to rank i mod world_size (order kept)."""
    return [int(i) for i in indices if int(i) % world_size == rank]


def shard_train_images(datamanager: Any, rank: int, world_size: int) -> None:
    """Make nerfstudio's full-image datamanager give this rank only its own images (i mod world_size == rank).

    nerfstudio 1.1.5's FullImageDatamanager ignores its rank: every rank shuffles all images with the same seed
    (train_cameras_sampling_seed) and would train on the same image at every step. Its shuffled epochs stay
    identical on every rank (same seed, same calls) and each rank keeps its own images of them, in that order. A
    fixed partition keeps each image's transient mask and its visit count on one rank."""
    if world_size <= 1:
        return
    everyone = datamanager.sample_train_cameras  # the datamanager's own sampler, same sequence on every rank

    def own_images() -> list[int]:
        return rank_images(everyone(), rank, world_size)

    datamanager.sample_train_cameras = own_images
    # the list drawn in __init__ (one epoch of all images): keep this rank's part of it
    datamanager.train_unseen_cameras = rank_images(datamanager.train_unseen_cameras, rank, world_size)


# ---------------------------------------------------------------------------------------------------- tensors
def _broadcast_(t: Tensor, src: int, device: torch.device) -> None:
    """Broadcast `t` in place from `src`, through `device` when the backend cannot send it where it is."""
    work = t.detach()
    if work.device != device or work.dtype == torch.bool:
        buf = work.to(device=device, dtype=torch.uint8 if work.dtype == torch.bool else work.dtype).contiguous()
        dist.broadcast(buf, src)
        work.copy_(buf.to(dtype=work.dtype))
    else:
        dist.broadcast(work, src)


def _structure(module: nn.Module) -> list[tuple[str, str, tuple[int, ...], str]]:
    params = (("parameter", n, t) for n, t in module.named_parameters())
    buffers = (("buffer", n, t) for n, t in module.named_buffers())
    return [(kind, n, tuple(t.shape), str(t.dtype)) for kind, n, t in itertools.chain(params, buffers)]


def check_same_structure(module: nn.Module) -> None:
    """Raise DataParallelError naming the first difference when the ranks' modules have different parameter /
    buffer names, shapes or dtypes (e.g. a setting resolved differently on one rank)."""
    rank, world_size = rank_and_world_size()
    if world_size <= 1:
        return
    mine = _structure(module)
    everyone: list[Any] = [None] * world_size
    dist.all_gather_object(everyone, mine)
    for r, theirs in enumerate(everyone):
        if theirs == mine:
            continue
        diff = next(((a, b) for a, b in itertools.zip_longest(mine, theirs) if a != b), None)
        raise DataParallelError(
            f"willags: rank {rank} and rank {r} built different models (first difference: {diff[0]} here, "
            f"{diff[1]} there); every rank must get the same configuration"
        )


@torch.no_grad()
def broadcast_module(module: nn.Module, src: int = 0) -> None:
    """Copy rank `src`'s parameters and buffers to every rank (what DDP does when it wraps a model): nerfstudio seeds
    rank r with seed + r, so random initialisations differ until then."""
    if rank_and_world_size()[1] <= 1:
        return
    check_same_structure(module)
    device = comm_device()
    for t in itertools.chain(module.parameters(), module.buffers()):
        _broadcast_(t, src, device)


def broadcast_int(value: int, src: int = 0) -> int:
    """`value` of rank `src` on every rank."""
    if rank_and_world_size()[1] <= 1:
        return int(value)
    t = torch.tensor([int(value)], dtype=torch.int64, device=comm_device())
    dist.broadcast(t, src)
    return int(t.item())


def average_gradients(params: Sequence[Tensor], world_size: int) -> None:
    """Replace every parameter's gradient by its mean over the ranks, in one all-reduce.

    A rank without a gradient for a parameter (unused this step) contributes zeros; a parameter no rank has a
    gradient for keeps grad None, so its optimiser skips it as it would in one process. `params` must be the same
    list, in the same order, on every rank (float32, like every willags parameter)."""
    if world_size <= 1 or not params:
        return
    for p in params:
        if p.dtype != torch.float32:
            raise DataParallelError(f"willags: data-parallel gradients are float32, got a {p.dtype} parameter")
    device = params[0].device
    present = torch.tensor([float(p.grad is not None) for p in params], device=device)
    grads = [(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params]
    flat = torch.cat([present, *grads])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    n_present = flat[: len(params)].tolist()
    flat = flat[len(params) :].div_(world_size)
    offset = 0
    for p, seen in zip(params, n_present, strict=True):
        n = p.numel()
        if seen > 0:
            mean = flat[offset : offset + n].view_as(p)
            if p.grad is None:
                p.grad = mean.clone()
            else:
                p.grad.copy_(mean)
        offset += n


def optimizer_parameters(optimizers: dict[str, torch.optim.Optimizer]) -> list[Tensor]:
    """Every parameter the optimisers step, in a fixed order (group name, then position). Read from the optimisers
    at each step: densification replaces the Gaussians' Parameter objects in the optimisers' param_groups."""
    out: list[Tensor] = []
    for name in sorted(optimizers):
        for group in optimizers[name].param_groups:
            out.extend(group["params"])
    return out


def all_reduce_strategy_state(state: dict[str, Any]) -> None:
    """gsplat DefaultStrategy state, in place, over the ranks: grad2d and count summed (the mean image-space gradient
    is then over every image of every rank since the last refinement), radii max."""
    if rank_and_world_size()[1] <= 1:
        return
    for key, op in (("grad2d", dist.ReduceOp.SUM), ("count", dist.ReduceOp.SUM), ("radii", dist.ReduceOp.MAX)):
        value = state.get(key)
        if isinstance(value, Tensor):
            dist.all_reduce(value, op=op)


@torch.no_grad()
def share_train_latents(latents: Tensor, seen: Tensor, image_idx: int) -> None:
    """Every rank's latent of this step's image ([D] row `image_idx` of `latents`, -1: none) written into every
    rank's `latents` / `seen`."""
    _, world_size = rank_and_world_size()
    if world_size <= 1:
        return
    device = comm_device()
    row = torch.full((latents.shape[1] + 1,), -1.0, device=device)
    if 0 <= image_idx < latents.shape[0] and bool(seen[image_idx]):
        row[0] = float(image_idx)
        row[1:] = latents[image_idx].to(device)
    rows = [torch.empty_like(row) for _ in range(world_size)]
    dist.all_gather(rows, row)
    for r in rows:
        i = int(r[0].item())
        if i >= 0:
            latents[i] = r[1:].to(latents.device, latents.dtype)
            seen[i] = True


def parameter_signature(tensors: Sequence[Tensor]) -> Tensor:
    """[len, 3] float64: (numel, sum, sum of |x|) of each tensor: equal on every rank when the tensors are."""
    rows = [
        torch.stack(
            [
                torch.tensor(float(t.numel()), device=t.device, dtype=torch.float64),
                t.detach().double().sum(),
                t.detach().double().abs().sum(),
            ]
        )
        for t in tensors
    ]
    return torch.stack(rows) if rows else torch.zeros(0, 3, dtype=torch.float64)


def check_parameters_agree(named: dict[str, Tensor], when: str) -> None:
    """Raise DataParallelError naming the tensor when the ranks' tensors `named` (same names, same order on every
    rank) differ: another count of Gaussians, or values whose sums disagree beyond AGREE_RTOL."""
    rank, world_size = rank_and_world_size()
    if world_size <= 1:
        return
    names = list(named)
    device = comm_device()
    mine = parameter_signature([named[n] for n in names]).to(device)
    everyone = [torch.empty_like(mine) for _ in range(world_size)]
    dist.all_gather(everyone, mine)
    for r, theirs in enumerate(everyone):
        close = torch.isclose(theirs, mine, rtol=AGREE_RTOL, atol=0.0)
        close[:, 0] = theirs[:, 0] == mine[:, 0]
        bad = (~close).any(dim=1).nonzero().flatten().tolist()
        if bad:
            i = bad[0]
            raise DataParallelError(
                f"willags: ranks disagree {when}: {names[i]!r} has {int(mine[i, 0])} values summing to "
                f"{mine[i, 1].item():.6g} on rank {rank}, {int(theirs[i, 0])} summing to {theirs[i, 1].item():.6g} "
                f"on rank {r}"
            )


# ---------------------------------------------------------------------------------------------------- densification
@contextmanager
def same_rng(seed: int, device: torch.device | str) -> Iterator[None]:
    """Run the body with the CPU generator (and `device`'s CUDA generator) seeded with `seed`; the caller's RNG
    state is restored afterwards, so each rank's own random stream (backgrounds, VAE samples) is unaffected."""
    dev = torch.device(device)
    cuda = [dev.index if dev.index is not None else torch.cuda.current_device()] if dev.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda):
        torch.default_generator.manual_seed(seed)
        for index in cuda:
            with torch.cuda.device(index):
                torch.cuda.manual_seed(seed)
        yield


def draw_refine_seed() -> int:
    """A seed for the refinements, drawn from rank 0's RNG (so it follows --machine.seed) and shared."""
    return broadcast_int(int(torch.randint(0, 2**31 - 1, (1,)).item()))


@dataclass
class RankSyncedStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy whose refinements agree over the ranks.

    Before growing: the statistics are all-reduced (`all_reduce_strategy_state`); growing (gsplat's split draws
    torch.randn offsets) runs under `same_rng(refine_seed + step)`; after pruning, the Gaussians are compared over
    the ranks (`check_parameters_agree`). With world_size == 1 only the seeding applies (what the tests' single-process
    reference uses). Hooks gsplat 1.4.0's DefaultStrategy._grow_gs / _prune_gs, which step_post_backward calls only
    at a refinement step, in that order."""

    refine_seed: int = 0
    """Base seed of the refinements' random draws (+ the step): the same on every rank."""
    world_size: int = 1
    """Number of ranks to all-reduce the statistics over (1: none)."""

    def _grow_gs(self, params, optimizers, state, step):  # type: ignore[override]
        if self.world_size > 1:
            all_reduce_strategy_state(state)
        with same_rng(self.refine_seed + step, params["means"].device):
            return super()._grow_gs(params, optimizers, state, step)

    def _prune_gs(self, params, optimizers, state, step):  # type: ignore[override]
        n_pruned = super()._prune_gs(params, optimizers, state, step)
        if self.world_size > 1:
            check_parameters_agree(dict(params.items()), f"after the refinement at step {step}")
        return n_pruned


def synced_strategy(strategy: DefaultStrategy, refine_seed: int, world_size: int) -> RankSyncedStrategy:
    """`strategy`'s settings in a RankSyncedStrategy."""
    if type(strategy) is not DefaultStrategy and not isinstance(strategy, RankSyncedStrategy):
        raise DataParallelError(
            f"willags: data-parallel training synchronises gsplat's DefaultStrategy, got {type(strategy).__name__}"
        )
    for hook in ("_grow_gs", "_prune_gs", "_update_state"):
        if not callable(getattr(DefaultStrategy, hook, None)):
            raise DataParallelError(
                f"willags: gsplat's DefaultStrategy has no {hook} (the pinned gsplat 1.4.0 has): data-parallel "
                "densification cannot be synchronised with this gsplat"
            )
    settings = {f.name: getattr(strategy, f.name) for f in fields(DefaultStrategy)}
    return RankSyncedStrategy(**settings, refine_seed=refine_seed, world_size=world_size)
