"""Data-parallel training of the willags methods over several devices (`ns-train willags --machine.num-devices N`).

nerfstudio's launcher starts one process per device and initialises torch.distributed (NCCL for
`--machine.device-type cuda`, gloo otherwise); its VanillaPipeline would then wrap the model in
DistributedDataParallel. DDP fixes its gradient buckets when it is built, and densification replaces the
Gaussians' parameters every `refine_every` steps, so WillagsPipeline does not wrap the model. Instead:

- every rank holds all Gaussians and appearance networks; rank 0's initial state is broadcast to the others
  (`broadcast_module`), after checking that every rank built the same parameter set;
- each rank trains on its own share of the training images (`shard_train_images`: image i belongs to rank
  i mod N, shuffled per epoch), so one step sees N different images, and decodes only those when nerfstudio caches
  them (`shard_image_cache`), in a background thread while the model is built (`ImageCachePrefetch`);
- after the backward pass and before the optimiser step, every gradient is summed over the ranks and divided by N
  (`GradientAverager`: one all-reduce through a buffer kept between steps, nothing read back on the host in a normal
  step; `average_gradients`, the first implementation, gives the same averages): one step is the single-process step
  on the *mean* loss of the N images. Averaged, not summed: the learning rates keep their meaning (Adam is
  scale-invariant anyway) and an average of identical values is a no-op, so gradient accumulation stays correct;
- densification statistics (gsplat's DefaultStrategy state: grad2d and count summed, radii max) are all-reduced
  just before each refinement, so every rank takes the same densify / prune decisions, and the refinement runs
  under the same RNG state on every rank (`same_rng`, seeded from rank 0's draw + the step), so split Gaussians get
  the same random offsets everywhere (no broadcast of the Gaussians afterwards). `check_parameters_agree` then
  compares the Gaussians' signatures over the ranks and stops with an error should they ever differ;
- each step's latent of a training image (the per-image embedding row or the VAE mean recorded in
  `train_latents`) is shared with every rank (riding in the gradients' all-reduce: `latent_row`,
  `apply_latent_rows`; or `share_train_latents`), so every rank's checkpoint and viewer know the appearances of all
  images;
- work every rank would repeat to the same end runs on rank 0 alone and its result reaches the others
  (`from_rank_zero`: the scene's inspection).

Per rank and not shared: the EMA teacher (computed from identical student weights, so it stays identical), the VAE
forward of the rank's own image, the transient masks of the rank's images and their per-image visit counts (image i
always lives on the same rank, so its mask cadence is the single-process one).

Every function here is a no-op or a plain computation for world_size == 1; the single-process path never calls them.
"""

import itertools
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

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


@dataclass
class DataParallelConfig:
    """How the ranks of a data-parallel run exchange gradients and images (`--pipeline.data-parallel.*`)."""

    reduction: Literal["buffer", "reference"] = "buffer"
    """"buffer": every gradient averaged in one all-reduce through a persistent buffer that also carries this step's
    training-image latents, nothing read back on the host unless this rank lacks a gradient that another rank may have
    (`GradientAverager`); "reference": the first implementation, kept to compare against (a new concatenation every
    step, the presence counts read back on the host, the latents gathered in a second collective and read back row by
    row: `average_gradients`, `share_train_latents`). Both give the same averages."""
    shard_image_cache: bool = True
    """Each rank decodes and caches only its own training images (image i belongs to rank i mod N); the others' slots
    hold placeholders of the right size that no step of this rank reads (`shard_image_cache`)."""
    step_profile: bool = False
    """Write each rank's per-step timings (forward, backward, gradient reduction and its bytes, the wait in the
    collective, optimiser, callbacks, the whole loop iteration; host clock, and CUDA events on a GPU) and its start-up
    phases to <run>/step_profile/ (willags_ns/engine/step_profile.py). Also on one device, to compare against."""


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


class Placeholder(torch.Tensor):
    """Another rank's training image in this rank's image cache: one value broadcast over the image's size. Pinning
    it returns it as it is: nerfstudio pins a host cache (past 500 training images) image by image, a broadcast
    tensor cannot be pinned, and none is needed (no step of this rank copies it to the device)."""

    def pin_memory(self, *args: Any, **kwargs: Any) -> Tensor:
        return self


def shard_image_cache(datamanager: Any, rank: int, world_size: int) -> None:
    """Make nerfstudio's full-image datamanager decode only this rank's training images when it caches them.

    nerfstudio 1.1.5 caches every training image on every rank (`cached_train`, loaded at the first step), though a
    rank only ever trains on its own (i mod world_size == rank). The dataset's `get_data` then returns, for another
    rank's image, a placeholder of the image's size (zeros, one value broadcast over the whole image unless the camera
    is distorted: nerfstudio undistorts a cached image with OpenCV, which needs a real array) without reading the file.
    The cameras are the same everywhere: undistortion changes a camera's intrinsics from its parameters alone. Must run
    before the first access to `cached_train`."""
    if world_size <= 1:
        return
    if "cached_train" in vars(datamanager):
        raise DataParallelError("willags: the training images were cached before the image cache was sharded")
    dataset = datamanager.train_dataset
    get_data = dataset.get_data
    cameras = dataset.cameras

    def own_or_placeholder(image_idx: int, image_type: str = "float32") -> dict[str, Any]:
        if int(image_idx) % world_size == rank:
            return get_data(image_idx, image_type=image_type)
        h, w = int(cameras.height[image_idx]), int(cameras.width[image_idx])
        dtype = torch.uint8 if image_type == "uint8" else torch.float32
        distortion = cameras.distortion_params
        flat = distortion is None or bool(torch.all(distortion[image_idx] == 0))
        if not flat:
            return {"image_idx": image_idx, "image": torch.zeros((h, w, 3), dtype=dtype)}
        image = torch.zeros((1, 1, 3), dtype=dtype).expand(h, w, 3).as_subclass(Placeholder)
        return {"image_idx": image_idx, "image": image}

    dataset.get_data = own_or_placeholder


class ImageCachePrefetch:
    """This rank's training images cached in a background thread while the model is built: nerfstudio caches them
    at the first access to `cached_train` (at the first step), one rank's share taking longer with several ranks per
    host than the whole collection on one device; decoding, undistorting and copying to the device mostly wait on
    files and native code, outside the interpreter lock. The cache is the same either way (the same images, the same
    placeholders); `wait` returns once it is complete and raises what the caching raised."""

    def __init__(self, datamanager: Any, device: Any):
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, args=(datamanager, device), name="willags-image-cache", daemon=True
        )
        self._thread.start()

    def _run(self, datamanager: Any, device: Any) -> None:
        try:
            dev = torch.device(str(device))
            if dev.type == "cuda" and dev.index is not None:
                torch.cuda.set_device(dev)  # the current device is per thread: this rank's, not cuda:0
            _ = datamanager.cached_train
        except BaseException as e:  # noqa: BLE001 - raised by wait(), in the pipeline's thread
            self._error = e

    def wait(self) -> None:
        self._thread.join()
        if self._error is not None:
            raise self._error


def is_placeholder(image: Tensor) -> bool:
    """Whether a cached image is `shard_image_cache`'s placeholder for another rank's image (one broadcast value)."""
    return image.dim() == 3 and image.numel() > 3 and image.stride()[:2] == (0, 0)


# ---------------------------------------------------------------------------------------------------- tensors
def _broadcast_(t: Tensor, src: int, device: torch.device) -> None:
    """Broadcast `t` in place from `src`, through `device` when the backend cannot send it where it is."""
    work = t.detach()
    if work.device != device or work.dtype == torch.bool or not work.is_contiguous():
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


def from_rank_zero(fn: Callable[[], Any]) -> tuple[Any, bool]:
    """``(fn()'s result, whether it ran here)``: with several ranks fn runs on rank 0 alone and its result (pickled)
    reaches every rank: for work every rank would repeat to the same end (the scene's inspection), which N ranks on
    one host would otherwise run N times at once. An exception on rank 0 is raised on every rank (a
    DataParallelError naming it there), so that none is left waiting."""
    rank, world_size = rank_and_world_size()
    if world_size <= 1:
        return fn(), True
    box: list[Any] = [None]
    if rank == 0:
        try:
            box[0] = ("ok", fn())
        except Exception as e:
            box[0] = ("error", e)
    dist.broadcast_object_list(box, src=0)
    status, value = box[0]
    if status == "error":
        if rank == 0:
            raise value
        raise DataParallelError(f"willags: rank 0 failed: {type(value).__name__}: {value}")
    return value, rank == 0


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


class GradientAverager:
    """Averages every gradient over the ranks in one all-reduce through a buffer kept from step to step; each rank's
    row of extra values (this step's training-image latent) rides along in the same collective.

    Buffer (float32, where the backend reduces): ``[P presence flags | the P gradients, in order | world_size rows of
    extra_width]``. Each rank writes 1.0 into the flag of every parameter it has a gradient for, its gradients (zeros
    where it has none: an unused parameter) and its own extra row (zeros in the other ranks' rows). After the sum the
    flags count the ranks with a gradient, the gradients are divided by N (the sum, then the division: the values of
    `average_gradients`), and row r holds rank r's extra values exactly (a value plus zeros). The averaged gradients
    become views into the buffer (no copy back), valid until the next call; nerfstudio sets them to None before the
    next backward.

    Why: the first implementation (`average_gradients`) copied every gradient into a new tensor each step and read
    the presence counts back on the host, which waits for the all-reduce to finish (and so for the slowest rank) before
    the host can queue the optimiser step. Here the host reads nothing back unless this rank lacks a gradient for a
    parameter: only then do the counts decide between another rank's mean and no gradient at all (None, skipped by its
    optimiser as in one process). `params` must be the same list, in the same order, on every rank (float32)."""

    def __init__(self, world_size: int):
        self.world_size = world_size
        self._buffer: Tensor | None = None
        self.bytes_reduced = 0
        """Bytes of the last all-reduce."""
        self.host_reads = 0
        """Host read-backs of the last call (0 unless this rank lacked a gradient)."""
        self.collective: tuple[Any, Any] | None = None
        """(before, after) hooks around the all-reduce (the step profile's CUDA events), or None."""

    def _buffer_of(self, numel: int, device: torch.device) -> Tensor:
        buf = self._buffer
        if buf is None or buf.numel() != numel or buf.device != device:
            buf = self._buffer = torch.empty(numel, dtype=torch.float32, device=device)
        return buf

    def average(self, params: Sequence[Tensor], extra: Tensor | None = None, extra_width: int = 0) -> Tensor | None:
        """Average the gradients of `params` in place (as `average_gradients` does) and return the ranks' extra rows
        ``[world_size, extra_width]`` (a view into the buffer: use it before the next call), or None without extras.
        `extra` is this rank's row ([extra_width]) or None (zeros)."""
        self.host_reads = 0
        self.bytes_reduced = 0
        n = self.world_size
        if n <= 1 or (not params and extra_width == 0):
            return None
        for p in params:
            if p.dtype != torch.float32:
                raise DataParallelError(f"willags: data-parallel gradients are float32, got a {p.dtype} parameter")
        device = comm_device()
        sizes = [p.numel() for p in params]
        n_flags, n_grads = len(params), sum(sizes)
        buf = self._buffer_of(n_flags + n_grads + n * extra_width, device)
        flags = torch.tensor([float(p.grad is not None) for p in params], dtype=torch.float32)
        if device.type == "cuda":  # pinned: an asynchronous copy, no wait for the device
            buf[:n_flags].copy_(flags.pin_memory(), non_blocking=True)
        else:
            buf[:n_flags].copy_(flags)
        grads = buf[n_flags : n_flags + n_grads]
        slots = list(grads.split(sizes)) if params else []
        if params:  # one kernel for every gradient (zeros for a parameter without one)
            own = buf.untyped_storage().data_ptr()
            flat = []
            for p in params:
                if p.grad is None:
                    flat.append(torch.zeros(p.numel(), device=device))
                elif p.grad.untyped_storage().data_ptr() == own:  # last call's view, accumulated into (not zeroed)
                    flat.append(p.grad.reshape(-1).clone())
                else:
                    flat.append(p.grad.reshape(-1))
            torch.cat(flat, out=grads)
        rows = buf[n_flags + n_grads :].view(n, extra_width) if extra_width else None
        if rows is not None:
            rows.zero_()
            if extra is not None:
                rows[rank_and_world_size()[0]].copy_(extra.reshape(-1))
        if self.collective is not None:
            self.collective[0]()
        dist.all_reduce(buf, op=dist.ReduceOp.SUM)
        if self.collective is not None:
            self.collective[1]()
        self.bytes_reduced = buf.numel() * buf.element_size()
        grads.div_(n)
        missing = [i for i, p in enumerate(params) if p.grad is None]
        seen = dict(zip(missing, buf[:n_flags][missing].tolist(), strict=True)) if missing else {}
        self.host_reads = 1 if missing else 0
        for i, (p, slot) in enumerate(zip(params, slots, strict=True)):
            if p.grad is not None or seen.get(i, 0.0) > 0:
                p.grad = slot.view_as(p)
        return rows


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


@torch.no_grad()
def latent_row(latents: Tensor, seen: Tensor, image_idx: int, device: torch.device) -> Tensor:
    """[D + 1] on `device`: (image_idx, its latent) when image `image_idx` has a recorded latent, else all -1, built
    on the device (whether the row is seen is not read back on the host)."""
    row = torch.full((latents.shape[1] + 1,), -1.0, device=device)
    if 0 <= image_idx < latents.shape[0]:
        known = seen[image_idx].to(device)
        row[0] = torch.where(known, float(image_idx), -1.0)
        row[1:] = torch.where(known, latents[image_idx].to(device, torch.float32), -1.0)
    return row


@torch.no_grad()
def apply_latent_rows(latents: Tensor, seen: Tensor, rows: Tensor) -> None:
    """Write every rank's row ([N, D + 1], `latent_row`'s format; index -1: none) into `latents` / `seen`, on the
    device and without reading anything back: each image row takes the value of the rank row naming it (at most one
    rank trains an image in a step), the others are kept."""
    rows = rows.to(latents.device)
    idx = rows[:, 0].round().long()  # [N], -1: none
    onehot = idx[:, None] == torch.arange(latents.shape[0], device=latents.device)[None, :]  # [N, n]
    hit = onehot.any(dim=0)  # [n]
    values = torch.where(onehot[..., None], rows[:, None, 1:].to(latents.dtype), 0.0).sum(dim=0)  # [n, D]
    latents.copy_(torch.where(hit[:, None], values, latents))
    seen.logical_or_(hit)


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
    grows_as: DefaultStrategy | None = None
    """A DefaultStrategy of its own kind whose growth this one runs, after the all-reduce (a budget on the growth:
    splats/splitclone.py), with this strategy's settings as they are at that step (the time budget refits them) and
    its own fields beyond gsplat's (the budget); None: gsplat's growth."""

    def _grow_gs(self, params, optimizers, state, step):  # type: ignore[override]
        if self.world_size > 1:
            all_reduce_strategy_state(state)
        with same_rng(self.refine_seed + step, params["means"].device):
            if self.grows_as is not None:  # on the all-reduced statistics: the same choice on every rank
                now = replace(self.grows_as, **default_strategy_settings(self))
                return now._grow_gs(params, optimizers, state, step)
            return super()._grow_gs(params, optimizers, state, step)

    def _prune_gs(self, params, optimizers, state, step):  # type: ignore[override]
        n_pruned = super()._prune_gs(params, optimizers, state, step)
        if self.world_size > 1:
            check_parameters_agree(dict(params.items()), f"after the refinement at step {step}")
        return n_pruned


def default_strategy_settings(strategy: DefaultStrategy) -> dict[str, Any]:
    """The values of gsplat's DefaultStrategy fields on `strategy` (any DefaultStrategy, of gsplat's kind or another)."""
    return {f.name: getattr(strategy, f.name) for f in fields(DefaultStrategy)}


def synced_strategy(strategy, refine_seed: int, world_size: int):
    """`strategy`'s settings in a RankSyncedStrategy (a DefaultStrategy of its own kind, such as one with a budget on
    its growth, grows through itself on the all-reduced statistics: `grows_as`); a strategy whose draws take a seed
    (MCMC densification: splats/mcmc.py, a `seed` field) gets `refine_seed`: its every move is then drawn alike on
    every rank."""
    if "seed" in {f.name for f in fields(strategy)} and not isinstance(strategy, DefaultStrategy):
        return replace(strategy, seed=refine_seed)
    if not isinstance(strategy, DefaultStrategy):
        raise DataParallelError(
            f"willags: data-parallel training synchronises gsplat's DefaultStrategy, got {type(strategy).__name__}"
        )
    for hook in ("_grow_gs", "_prune_gs", "_update_state"):
        if not callable(getattr(DefaultStrategy, hook, None)):
            raise DataParallelError(
                f"willags: gsplat's DefaultStrategy has no {hook} (the pinned gsplat 1.4.0 has): data-parallel "
                "densification cannot be synchronised with this gsplat"
            )
    settings = default_strategy_settings(strategy)
    grows_as = strategy.grows_as if isinstance(strategy, RankSyncedStrategy) else strategy
    if type(grows_as) is DefaultStrategy:
        grows_as = None
    return RankSyncedStrategy(**settings, refine_seed=refine_seed, world_size=world_size, grows_as=grows_as)
