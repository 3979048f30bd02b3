import pytest
import torch
from torch import nn

from willags_ns.mask.teacher import TeacherConfig, ema_update_, make_teacher


class _Net(nn.Module):
    def __init__(self, width=4):
        super().__init__()
        self.lin = nn.Linear(3, width)
        self.register_buffer("count", torch.zeros(()))


def _pair():
    torch.manual_seed(0)
    student = _Net()
    teacher = make_teacher(student)
    with torch.no_grad():
        for p in student.parameters():
            p.add_(torch.randn_like(p))
        student.get_buffer("count").fill_(7)
    return teacher, student


def test_make_teacher_is_frozen_copy():
    student = _Net()
    teacher = make_teacher(student)
    assert not teacher.training
    assert all(not p.requires_grad for p in teacher.parameters())
    assert all(p.requires_grad for p in student.parameters())
    for (n, p), (_, q) in zip(teacher.named_parameters(), student.named_parameters(), strict=True):
        torch.testing.assert_close(p, q)
        assert p.data_ptr() != q.data_ptr(), n


def test_tau_zero_copies():
    teacher, student = _pair()
    ema_update_(teacher, student, 0.0)
    for p, q in zip(teacher.parameters(), student.parameters(), strict=True):
        assert torch.equal(p, q)
    assert teacher.get_buffer("count").item() == 7


def test_tau_one_freezes_params():
    teacher, student = _pair()
    before = [p.clone() for p in teacher.parameters()]
    ema_update_(teacher, student, 1.0)
    for p, b in zip(teacher.parameters(), before, strict=True):
        assert torch.equal(p, b)


def test_tau_half_is_halfway_and_repeated_updates_converge():
    teacher, student = _pair()
    before = [p.clone() for p in teacher.parameters()]
    ema_update_(teacher, student, 0.5)
    for p, b, q in zip(teacher.parameters(), before, student.parameters(), strict=True):
        torch.testing.assert_close(p, 0.5 * (b + q))
    teacher, student = _pair()
    before = [p.clone() for p in teacher.parameters()]
    for _ in range(100):
        ema_update_(teacher, student, 0.99)
    for p, b, q in zip(teacher.parameters(), before, student.parameters(), strict=True):
        # after k steps the remaining gap is tau**k = 0.99**100 = 0.366
        torch.testing.assert_close(p - q, 0.99**100 * (b - q), atol=1e-5, rtol=1e-4)


def test_teacher_does_not_track_student_grads():
    teacher, student = _pair()
    ema_update_(teacher, student, 0.9)
    assert all(not p.requires_grad for p in teacher.parameters())
    assert all(p.grad_fn is None for p in teacher.parameters())


def test_mismatch_raises():
    with pytest.raises(ValueError):
        ema_update_(_Net(4), _Net(5), 0.5)  # shapes
    other = nn.Sequential(nn.Linear(3, 4))
    with pytest.raises(ValueError):
        ema_update_(_Net(4), other, 0.5)  # names
    with pytest.raises(ValueError):
        ema_update_(_Net(4), _Net(4), 1.5)


def test_default_tau():
    assert 0.9 < TeacherConfig().tau < 1.0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_update():
    teacher, student = _pair()
    expected = [0.9 * p + 0.1 * q for p, q in zip(teacher.parameters(), student.parameters(), strict=True)]
    teacher, student = teacher.cuda(), student.cuda()
    ema_update_(teacher, student, 0.9)
    for p, e in zip(teacher.parameters(), expected, strict=True):
        torch.testing.assert_close(p.cpu(), e)
