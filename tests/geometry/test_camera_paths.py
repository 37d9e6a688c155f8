"""Camera paths for videos: the interpolation passes through both context cameras with proper
rotations, and the wobble circles each context camera at the asked radius."""

import math

import torch

from usplat_dr.geometry.camera_paths import camera_path, slerp
from usplat_dr.geometry.quaternions import quat_xyzw_to_matrix


def two_cameras() -> torch.Tensor:
    c = torch.eye(4).repeat(2, 1, 1)
    angle = math.radians(30)  # the second camera turned about +Y and moved along +X
    c[1, :3, :3] = quat_xyzw_to_matrix(torch.tensor([0.0, math.sin(angle / 2), 0.0,
                                                     math.cos(angle / 2)]))
    c[1, 0, 3] = 2.0
    return c


def test_path_goes_from_context_0_to_context_1_and_back():
    cams, frames = two_cameras(), 20
    path = camera_path(cams, frames)
    assert path.shape == (frames, 4, 4)
    # float32 path from float64 maths: agreement to float32 rounding of unit-size entries
    torch.testing.assert_close(path[0], cams[0], atol=1e-6, rtol=0)
    torch.testing.assert_close(path[frames // 4], cams[1], atol=1e-6, rtol=0)  # t = 1
    rot = path[:, :3, :3].double()
    eye = torch.eye(3, dtype=torch.float64).expand_as(rot)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), eye, atol=1e-6, rtol=0)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(frames, dtype=torch.float64))


def test_wobble_circles_each_context_camera_at_the_radius():
    cams, frames, wobble = two_cameras(), 20, 0.25
    path = camera_path(cams, frames, wobble=wobble)
    radius = wobble * 2.0  # x the baseline between the two cameras
    first, second = path[10:15], path[15:]  # half the wobble around each context camera
    for part, cam in ((first, cams[0]), (second, cams[1])):
        offsets = part[:, :3, 3] - cam[:3, 3]
        torch.testing.assert_close(offsets.norm(dim=-1), torch.full((5,), radius),
                                   atol=1e-6, rtol=0)
        assert torch.equal(part[:, :3, :3], cam[:3, :3].expand(5, 3, 3))  # same orientation


def test_slerp_keeps_unit_length_and_ends():
    q0 = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    q1 = torch.tensor([math.cos(0.5), math.sin(0.5), 0, 0], dtype=torch.float64)
    assert torch.allclose(slerp(q0, q1, 0.0), q0) and torch.allclose(slerp(q0, q1, 1.0), q1)
    half = slerp(q0, q1, 0.5)
    assert math.isclose(float(half.norm()), 1.0, rel_tol=1e-12)
    assert math.isclose(float(half[1]), math.sin(0.25), rel_tol=1e-12)  # half the angle
