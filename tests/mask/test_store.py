"""The masks kept between an image's visits: one bit a pixel, read back bit for bit."""

import pytest
import torch

from willags_ns.mask.store import PackedMasks, pack_bits, unpack_bits


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (8, 8), (37, 53), (600, 800)])
def test_unpack_gives_back_every_bit(shape):
    g = torch.Generator().manual_seed(shape[0] * 1000 + shape[1])
    mask = torch.rand(shape, generator=g) < 0.3
    packed = pack_bits(mask)
    assert packed.dtype == torch.uint8
    assert packed.numel() == -(-mask.numel() // 8)
    back = unpack_bits(packed, shape)
    assert back.dtype == torch.bool and back.shape == mask.shape
    assert torch.equal(back, mask)


def test_bit_order_is_row_major_low_bit_first():
    mask = torch.zeros(2, 8, dtype=torch.bool)
    mask[0, 0] = mask[0, 7] = mask[1, 1] = True
    assert pack_bits(mask).tolist() == [1 + 128, 2]


def test_too_few_bytes_for_the_shape_is_refused():
    with pytest.raises(ValueError, match="fewer than the 17 pixels"):
        unpack_bits(torch.zeros(2, dtype=torch.uint8), (1, 17))


def test_packed_masks_hold_an_eighth_of_a_bool_tensor():
    masks = PackedMasks()
    full = torch.ones(560, 800, dtype=torch.bool)
    for i in range(4):
        masks[i] = full if i % 2 else ~full
    assert len(masks) == 4 and 3 in masks and 7 not in masks
    assert masks.nbytes() * 8 == 4 * full.numel()
    assert masks[1].all() and not masks[2].any()
    del masks[2]
    assert sorted(masks) == [0, 1, 3]
    masks.clear()
    assert len(masks) == 0 and masks.nbytes() == 0


def test_packed_masks_take_bool_masks_only():
    with pytest.raises(TypeError, match="image 5's mask is torch.float32, not bool"):
        PackedMasks()[5] = torch.ones(4, 4)


def test_a_reused_mask_is_the_mask_the_teacher_step_made():
    """Between two teacher renders an image is supervised by the mask the last one made, exactly."""
    from tests.test_model import _tiny_model

    model = _tiny_model()
    model.config.mask.safeguard.enabled = False
    model.train()
    model.step = model.config.mask.warmup_steps + 10
    assert isinstance(model.mask_step.masks, PackedMasks)
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(31, 45, 3, generator=g)
    teacher = gt.clone()
    teacher[5:20, 10:30] = 1.0 - teacher[5:20, 10:30]  # a transient: the photo differs from the teacher there
    made = model.step_static_mask({"image_idx": 0, "teacher_rgb": teacher}, gt)
    assert made.distance is not None and made.mask is not None
    assert 0 < made.mask.sum() < made.mask.numel()  # some pixels masked, not all
    reused = model.step_static_mask({"image_idx": 0}, gt)
    assert reused.distance is None and reused.mask is not None
    assert torch.equal(reused.mask, made.mask)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_masks_pack_and_unpack_on_the_gpu_as_on_the_cpu():
    g = torch.Generator().manual_seed(7)
    mask = torch.rand(301, 467, generator=g) < 0.5
    packed = pack_bits(mask.cuda())
    assert packed.is_cuda and torch.equal(packed.cpu(), pack_bits(mask))
    assert torch.equal(unpack_bits(packed, mask.shape).cpu(), mask)
