"""render/camera.py: the intrinsics at a render scale, bit for bit nerfstudio's rescale-then-read path, without
changing the camera and, given the camera's size, without reading it (on a GPU a read is a wait for the device)."""

import copy

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from willags_ns.render.camera import camera_view, intrinsics_at, scaled_size

SIZES = [(601, 401), (640, 480), (7, 5), (1, 1), (1023, 769), (4001, 2999), (333, 999)]
SCALES = [1, 2, 4, 8]


class UnreadableSize(torch.Tensor):
    """A camera's width or height that fails whenever anything uses it: proves a path never reads it."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        raise AssertionError(f"the camera's size was read ({getattr(func, '__name__', func)})")


def camera(width: int, height: int, seed: int = 0) -> Cameras:
    """One pinhole camera with intrinsics that use every bit of float32's mantissa."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width + torch.rand(1, 1, generator=g)
    return Cameras(
        camera_to_worlds=torch.eye(4)[:3][None].clone(),
        fx=f,
        fy=f * 1.0137,
        cx=width / 2 + torch.rand(1, 1, generator=g),
        cy=height / 2 - torch.rand(1, 1, generator=g),
        width=torch.tensor([[width]]),
        height=torch.tensor([[height]]),
        camera_type=CameraType.PERSPECTIVE,
    )


def nerfstudios(cam: Cameras, scale: float) -> tuple[torch.Tensor, int, int]:
    """What nerfstudio's own calls give: rescale the camera (a copy) by 1 / scale, then read K and the size."""
    c = copy.deepcopy(cam)
    c.rescale_output_resolution(1 / scale)
    return c.get_intrinsics_matrices(), int(c.width.item()), int(c.height.item())


def unreadable_size(cam: Cameras) -> Cameras:
    cam.width = cam.width.as_subclass(UnreadableSize)
    cam.height = cam.height.as_subclass(UnreadableSize)
    return cam


@pytest.mark.parametrize("scale", SCALES)
def test_intrinsics_at_equals_nerfstudios_rescale_bit_for_bit_and_leaves_the_camera_alone(scale):
    for i, (w, h) in enumerate(SIZES):
        cam = camera(w, h, seed=i)
        fields = {k: getattr(cam, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}
        values = {k: v.clone() for k, v in fields.items()}
        want_K, want_w, want_h = nerfstudios(cam, scale)
        for size in (None, (w, h)):  # read from the camera, or known on the host
            K, W, H = intrinsics_at(cam, scale, "cpu", size)
            assert (W, H) == (want_w, want_h), (w, h, scale, size)
            assert K.dtype == want_K.dtype == torch.float32 and torch.equal(K, want_K), (w, h, scale, size)
            assert type(W) is int and type(H) is int
        for k, v in fields.items():  # the same tensors, the same values: the camera is not rescaled and restored
            assert getattr(cam, k) is v and torch.equal(v, values[k]), k
    # the odd sizes floor as nerfstudio does (601 / 2 -> 300), where its rescale back up gave the camera 600
    assert scaled_size(601, 401, 1 / 2) == (300, 200) and scaled_size(7, 5, 1 / 4) == (1, 1)


def test_a_known_size_is_used_without_reading_the_cameras_size():
    cam = unreadable_size(camera(601, 401))
    reference = camera(601, 401)
    for scale in SCALES:
        K, W, H = intrinsics_at(cam, scale, "cpu", (601, 401))
        want_K, want_w, want_h = nerfstudios(reference, scale)
        assert torch.equal(K, want_K) and (W, H) == (want_w, want_h)
    view = camera_view(cam, cam.camera_to_worlds, 2, "cpu", (601, 401))
    assert (view.width, view.height) == (300, 200) and view.viewmat.shape == (1, 4, 4)
    with pytest.raises(AssertionError, match="size was read"):  # without the size, the camera is read
        intrinsics_at(cam, 2, "cpu")


def test_intrinsics_at_keeps_several_cameras_and_the_requested_device():
    cams = Cameras(
        camera_to_worlds=torch.eye(4)[:3][None].repeat(3, 1, 1),
        fx=torch.tensor([[100.3], [200.7], [300.1]]),
        fy=torch.tensor([[101.3], [201.7], [301.1]]),
        cx=torch.tensor([[50.5], [60.5], [70.5]]),
        cy=torch.tensor([[40.25], [30.25], [20.25]]),
        width=torch.tensor([[101], [101], [101]]),
        height=torch.tensor([[81], [81], [81]]),
    )
    c = copy.deepcopy(cams)
    c.rescale_output_resolution(1 / 4)
    K, W, H = intrinsics_at(cams, 4, torch.device("cpu"), (101, 81))
    assert K.shape == (3, 3, 3) and torch.equal(K, c.get_intrinsics_matrices()) and (W, H) == (25, 20)
    with pytest.raises(ValueError, match="one camera at a time"):  # several sizes: which one is not for it to pick
        intrinsics_at(cams, 4, "cpu")
