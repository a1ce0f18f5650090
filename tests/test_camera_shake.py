"""Camera shake as a learnt rotation path (gsmsdr_ns.blur.shake): basis, homographies, the warp average, learning.

Pure functions on small tensors; no nerfstudio.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from gsmsdr_ns.blur.shake import (
    CameraShake,
    apply_camera_shake,
    apply_camera_shake_occluding,
    apply_camera_shake_with_depth,
    parallax_rotvecs,
    rotation_homographies,
    shake_basis,
    shake_mean_kernel,
    shake_sample_grid,
    shake_splat_positions,
    visible_sample_depths,
)

K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])  # 64 x 48, principal point at the centre


def textured(seed: int = 0, height: int = 48, width: int = 64) -> torch.Tensor:
    """[1, 3, H, W] smooth random texture in [0, 1]."""
    gen = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, height // 4, width // 4, generator=gen)
    return F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)


def fit(model: torch.nn.Module, loss, steps: int) -> None:
    """``steps`` Adam steps (the preset's path rate, 0.1) on ``loss()``."""
    optimiser = torch.optim.Adam(model.parameters(), lr=0.1, eps=1e-8)
    for _ in range(steps):
        optimiser.zero_grad()
        loss().backward()
        optimiser.step()


def apply_h(H: torch.Tensor, xy) -> torch.Tensor:
    p = H @ torch.tensor([xy[0], xy[1], 1.0], dtype=H.dtype)
    return p[:2] / p[2]


@pytest.mark.parametrize("n", [2, 5, 9])
def test_basis_centred_has_zero_mean_and_the_other_passes_through_the_pose(n):
    centred, through = shake_basis(n, centred=True), shake_basis(n, centred=False)
    assert centred.shape == through.shape == (n, 3)
    assert torch.allclose(centred.mean(dim=0), torch.zeros(3), atol=1e-7)
    tau = (torch.arange(n) + 0.5) / n - 0.5
    assert torch.allclose(through[:, 0], tau) and torch.allclose(through[:, 2], tau**3)
    if n % 2:  # the middle sample is mid-exposure: no rotation there
        assert torch.equal(through[n // 2], torch.zeros(3))
    with pytest.raises(ValueError, match="at least 2 samples"):
        shake_basis(1, centred=True)


def test_rotation_homographies_move_pixels_as_a_turning_camera_does():
    """Identity for no rotation; a turn about the camera's y axis by a moves the principal point by f tan(a)
    horizontally; a roll keeps the principal point and moves the corners (blur that varies across the image)."""
    centre = (31.5, 23.5)  # the principal point in pixel-index coordinates (pixel centres at integers)
    H = rotation_homographies(K, torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]]))
    assert torch.allclose(H[0], torch.eye(3), atol=1e-5)
    moved = apply_h(H[1], centre)
    assert abs(abs(float(moved[0]) - centre[0]) - 60.0 * math.tan(0.05)) < 1e-3
    assert abs(float(moved[1]) - centre[1]) < 1e-4
    assert torch.allclose(apply_h(H[2], centre), torch.tensor(centre), atol=1e-4)
    corner = apply_h(H[2], (0.0, 0.0)) - torch.tensor([0.0, 0.0])
    assert float(corner.norm()) == pytest.approx(0.05 * math.hypot(31.5, 23.5), rel=0.05)


def test_apply_camera_shake_is_the_identity_without_motion_and_averages_the_warps():
    image = textured()
    still = rotation_homographies(K, torch.zeros(4, 3))
    assert torch.allclose(apply_camera_shake(image, still, linear_light=False), image, atol=1e-5)
    assert torch.allclose(apply_camera_shake(image, still, linear_light=True), image, atol=1e-4)
    # two samples one pixel left and right of the pose: the average of the two shifted images (away from the border;
    # a long lens, so that a turn shifts every pixel by nearly the same amount)
    long_lens = K.clone()
    long_lens[0, 0] = long_lens[1, 1] = 600.0
    a = math.atan(1.0 / 600.0)
    paths = torch.tensor([[0.0, a, 0.0], [0.0, -a, 0.0]])
    both = apply_camera_shake(image, rotation_homographies(long_lens, paths), linear_light=False)
    expected = 0.5 * (image[..., 1:-1, :-2] + image[..., 1:-1, 2:])
    assert torch.allclose(both[..., 1:-1, 1:-1], expected, atol=2e-3)
    with pytest.raises(ValueError, match=r"\[1, C, H, W\]"):
        apply_camera_shake(image[0], still)
    with pytest.raises(ValueError, match=r"\[T, 3, 3\]"):
        apply_camera_shake(image, still[0])


def test_a_shake_path_is_learnt_back_from_the_photo_it_blurred():
    """A blur made along a known path (about 2 pixels of turn, with roll) is fitted from the module's small random
    start with Adam: the loss falls by orders of magnitude, and the blur at the start gets a non-zero gradient."""
    image = textured(1)
    view = torch.tensor([0])
    truth = CameraShake(1, num_samples=9, initial_radians=0.0)
    with torch.no_grad():
        truth.coefficients.copy_(torch.tensor([[[1.5, 4.0, 0.5], [0.0, 2.0, 0.0], [-3.0, 0.0, 1.0]]]))
    target = truth(image, K, view, centred=True).detach()
    model = CameraShake(1, num_samples=9, seed=3)
    inner = (Ellipsis, slice(6, -6), slice(6, -6))  # the border reads replicated pixels in both

    def loss() -> torch.Tensor:
        return ((model(image, K, view, centred=True) - target)[inner] ** 2).mean()

    first = loss()
    first.backward()
    assert model.coefficients.grad is not None and float(model.coefficients.grad.abs().sum()) > 0
    fit(model, loss, steps=150)
    assert float(loss()) < 0.02 * float(first)


def test_initial_paths_are_small_and_leave_the_global_random_stream_alone():
    torch.manual_seed(5)
    expected = torch.rand(3)
    torch.manual_seed(5)
    shake = CameraShake(6, num_samples=9)
    assert torch.equal(torch.rand(3), expected)
    rotvecs = shake.rotvecs(torch.tensor([2]), centred=True)
    assert rotvecs.shape == (9, 3) and 0 < float(rotvecs.abs().max()) < 0.01
    assert torch.equal(CameraShake(6, num_samples=9).coefficients, shake.coefficients)  # seeded: reproducible


def test_the_depth_grid_without_translation_is_the_rotation_homography():
    """With zero translations the depth-aware warp reads where the homography warp reads, whatever the depth."""
    image = textured(2)
    rotvecs = torch.tensor([[0.01, -0.02, 0.03], [0.0, 0.0, 0.0], [-0.02, 0.01, -0.01]])
    depth = 0.5 + torch.rand(48, 64, generator=torch.Generator().manual_seed(0)) * 4.0
    grid = shake_sample_grid(K, rotvecs, torch.zeros(3, 3), depth)
    assert grid.shape == (3, 48, 64, 2)
    by_depth = apply_camera_shake_with_depth(image, grid, linear_light=True)
    by_homography = apply_camera_shake(image, rotation_homographies(K, rotvecs), linear_light=True)
    assert torch.allclose(by_depth, by_homography, atol=1e-4)


def test_a_translation_moves_near_points_further_than_far_ones():
    """A sideways move of c scene units shifts a pixel at depth z by f c / z: 2 px at depth 1.5, 1 px at depth 3."""
    depth = torch.full((48, 64), 1.5)
    depth[:, 32:] = 3.0
    grid = shake_sample_grid(K, torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]), depth)
    pixels_x = (grid[..., 0] + 1.0) * (64 - 1) / 2.0
    pixels_y = (grid[..., 1] + 1.0) * (48 - 1) / 2.0
    columns = torch.arange(64, dtype=torch.float32).expand(48, 64)
    assert torch.allclose(pixels_x[0], columns, atol=1e-4)
    shift = pixels_x[1] - columns
    assert torch.allclose(shift[:, :32], torch.full((48, 32), 2.0), atol=1e-4)
    assert torch.allclose(shift[:, 32:], torch.full((48, 32), 1.0), atol=1e-4)
    assert torch.allclose(pixels_y[1], torch.arange(48, dtype=torch.float32)[:, None].expand(48, 64), atol=1e-4)


def test_a_translating_shake_path_needs_depth_and_learns_from_the_start():
    """The translation path starts at rest, is fitted from a blur made by a moving camera over two depths (which
    no rotation path can make), and the module refuses to run without the render's depth."""
    image = textured(3)
    view = torch.tensor([0])
    depth = torch.full((48, 64), 1.0)
    depth[24:] = 3.0
    truth = CameraShake(1, num_samples=9, initial_radians=0.0, translation=True)
    with torch.no_grad():
        truth.translation_coefficients.copy_(torch.tensor([[[6.0, 0.0, 0.0], [0.0, 3.0, 0.0], [2.0, 0.0, 0.0]]]))
    target = truth(image, K, view, centred=True, depth=depth).detach()
    model = CameraShake(1, num_samples=9, seed=3, translation=True)
    assert model.translation_coefficients is not None and float(model.translation_coefficients.abs().sum()) == 0
    assert CameraShake(1).translation_coefficients is None
    with pytest.raises(ValueError, match="depth"):
        model(image, K, view, centred=True)
    inner = (Ellipsis, slice(6, -6), slice(6, -6))

    def loss() -> torch.Tensor:
        return ((model(image, K, view, centred=True, depth=depth) - target)[inner] ** 2).mean()

    first = loss()
    fit(model, loss, steps=200)
    assert float(loss()) < 0.05 * float(first)


def test_parallax_rotations_cancel_a_translation_at_the_reference_depth_only():
    """Offset by :func:`parallax_rotvecs`, a sideways move leaves points at the reference depth about where they
    were (first order), moves nearer points one way and farther points the other."""
    depth = torch.full((48, 64), 2.0)
    depth[:, :21] = 1.0
    depth[:, 43:] = 4.0
    translations = torch.tensor([[0.02, -0.01, 0.0]])
    rotvecs = parallax_rotvecs(translations, torch.tensor(2.0))
    assert torch.allclose(rotvecs, torch.tensor([[0.005, 0.01, 0.0]]))
    grid = shake_sample_grid(K, rotvecs, translations, depth)
    pixels_x = (grid[0, ..., 0] + 1.0) * (64 - 1) / 2.0
    shift = pixels_x - torch.arange(64, dtype=torch.float32)
    # f c_x (1/z - 1/z_ref): +0.6 px at depth 1, 0 at 2, -0.3 px at 4 (60 px focal, 0.02 units); 22 px off the
    # axis a rotation moves a pixel about 13 % further than at the centre, so the cancellation is approximate there
    assert shift[24, 32].abs() < 0.02
    assert abs(float(shift[24, 10]) - 0.6) < 0.1 and abs(float(shift[24, 54]) + 0.3) < 0.1


def test_a_parallax_path_rotates_only_before_its_translations_start():
    """``translate=False`` is the rotation path alone (its translations get no gradient); with ``translate`` and
    ``parallax`` a constant-depth render is blurred about as by the rotations alone, where the same translations
    without ``parallax`` blur it further."""
    image = textured(4)
    view = torch.tensor([0])
    model = CameraShake(1, num_samples=5, seed=1, translation=True, parallax=True)
    with torch.no_grad():
        model.translation_coefficients.copy_(torch.tensor([[[20.0, -10.0, 0.0], [0.0, 5.0, 0.0], [5.0, 0.0, 0.0]]]))
    rotation_only = apply_camera_shake(image, rotation_homographies(K, model.rotvecs(view, True)), linear_light=True)
    unmoved = model(image, K, view, centred=True, translate=False)
    assert torch.equal(unmoved, rotation_only)
    unmoved.sum().backward()
    assert model.translation_coefficients.grad is None
    flat_depth = torch.full((48, 64), 2.0)
    inner = (Ellipsis, slice(6, -6), slice(6, -6))
    parallax_change = (model(image, K, view, centred=True, depth=flat_depth) - rotation_only)[inner].abs().max()
    moving = CameraShake(1, num_samples=5, seed=1, translation=True)
    moving.load_state_dict(model.state_dict())
    moving_change = (moving(image, K, view, centred=True, depth=flat_depth) - rotation_only)[inner].abs().max()
    assert moving_change > 0.05 and parallax_change < 0.2 * moving_change


def test_the_path_kernel_of_a_still_camera_is_a_point_and_a_pan_spreads_it_along_x():
    """The image-mean kernel of a rotation path: a point for no rotation; for a pan (yaw) a horizontal streak whose
    spread is the path's (f times the angle, a little more off the axis), centred and summing to 1."""
    still = shake_mean_kernel(K, torch.zeros(9, 3), 48, 64, 15)
    assert still.shape == (1, 15, 15) and float(still[0, 7, 7]) == pytest.approx(1.0)
    tau = shake_basis(9, centred=True)[:, 0]
    angle = 0.1  # radians over the exposure: 6 px at f = 60
    rotvecs = torch.zeros(9, 3)
    rotvecs[:, 1] = angle * tau
    kernel = shake_mean_kernel(K, rotvecs, 48, 64, 15)[0].double()
    assert float(kernel.sum()) == pytest.approx(1.0) and bool((kernel >= 0).all())
    offsets = torch.arange(15, dtype=torch.float64) - 7
    col, row = kernel.sum(dim=0), kernel.sum(dim=1)
    mean_x, mean_y = float((col * offsets).sum()), float((row * offsets).sum())
    var_x = float((col * (offsets - mean_x) ** 2).sum())
    var_y = float((row * (offsets - mean_y) ** 2).sum())
    on_axis = float((60.0 * angle * tau).var(unbiased=False))
    assert abs(mean_x) < 0.05 and abs(mean_y) < 0.05
    assert on_axis < var_x < 1.8 * on_axis and var_y < 0.1 * var_x
    with pytest.raises(ValueError, match="max_size"):
        shake_mean_kernel(K, rotvecs, 48, 64, 14)


def test_the_path_kernel_of_a_wide_shake_is_clamped_to_its_window():
    """A path longer than the window keeps all its mass on the window (border taps), so the loss's kernel still
    sums to 1."""
    rotvecs = torch.zeros(9, 3)
    rotvecs[:, 0] = 1.0 * shake_basis(9, centred=True)[:, 0]  # 60 px of tilt
    kernel = shake_mean_kernel(K, rotvecs, 48, 64, 9)[0]
    assert float(kernel.sum()) == pytest.approx(1.0, abs=1e-5)
    assert float(kernel[0].sum() + kernel[-1].sum()) > 0.3 and bool(torch.isfinite(kernel).all())


def near_square_over_background():
    """A 64 x 24 view: a white square of columns 24-39 at depth 2 in front of a textured wall at depth 10, and a
    camera moving sideways so that the square shifts 0 / +-5 / +-10 px and the wall 0 / +-1 / +-2 px (whole pixels,
    so every warp is exact) -> (image, K, translations, depth, the average of the five views composited with the
    square in front)."""
    height, width = 24, 64
    K_view = torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 12.0], [0.0, 0.0, 1.0]])
    u = torch.arange(width, dtype=torch.float32)

    def wall(x: torch.Tensor) -> torch.Tensor:
        return 0.5 + 0.4 * torch.sin(x / 3.0)

    square = (u >= 24) & (u < 40)
    depth = torch.where(square, 2.0, 10.0).expand(height, width).clone()
    image = torch.where(square, torch.ones(width), wall(u)).expand(1, 3, height, width).clone()
    steps = torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0])
    translations = torch.stack([0.2 * steps, torch.zeros(5), torch.zeros(5)], dim=1)
    views = []
    for c in (0.2 * steps).tolist():  # the camera moved by c sees depth z shifted by -f c / z
        seen_square = (u + 25.0 * c >= 24) & (u + 25.0 * c < 40)
        views.append(torch.where(seen_square, torch.ones(width), wall(u + 5.0 * c)))
    return image, K_view, translations, depth, torch.stack(views).mean(dim=0)


def test_forward_positions_invert_the_backward_grid():
    """A pixel's point projected into a time sample's camera (:func:`shake_splat_positions`), read back by that
    sample's grid at its depth there, lands on the pixel it came from: the two warps are one camera motion."""
    depth = 1.0 + torch.rand(48, 64, generator=torch.Generator().manual_seed(1)) * 3.0
    rotvecs = torch.tensor([[0.01, -0.02, 0.015], [-0.01, 0.005, 0.0]])
    translations = torch.tensor([[0.03, -0.02, 0.01], [-0.01, 0.02, -0.02]])
    positions, sample_depth = shake_splat_positions(K, rotvecs, translations, depth)
    assert positions.shape == (2, 48, 64, 2) and sample_depth.shape == (2, 48, 64)
    assert not torch.allclose(positions[0], positions[1])
    for t in range(2):
        p = positions[t, 20, 30]
        # the grid of a view whose every pixel lies at the point's depth in sample t, read at p (bilinear: the map is
        # smooth at one depth)
        at_point = torch.full((1, 48, 64), float(sample_depth[t, 20, 30]))
        grid_t = shake_sample_grid(K, rotvecs[t : t + 1], translations[t : t + 1], at_point)
        sampled = F.grid_sample(
            grid_t.permute(0, 3, 1, 2),
            torch.stack([p[0] / 63 * 2 - 1, p[1] / 47 * 2 - 1]).view(1, 1, 1, 2),
            align_corners=True,
        )
        back = (sampled.view(2) + 1.0) * torch.tensor([63.0, 47.0]) / 2.0
        assert torch.allclose(back, torch.tensor([30.0, 20.0]), atol=0.05), (t, back)


def test_visible_depths_see_the_near_square_where_it_moved():
    """Each time sample's z-buffer holds the square's depth where the square moved to (over the wall) and the
    wall's where nothing nearer landed; a still camera sees the render's own depth."""
    _, K_view, translations, depth, _ = near_square_over_background()
    still = visible_sample_depths(K_view, torch.zeros(5, 3), torch.zeros(5, 3), depth)
    assert torch.equal(still, depth.expand(5, 24, 64))
    visible = visible_sample_depths(K_view, torch.zeros(5, 3), translations, depth)
    # sample 0: c = -0.4, the square shifted +10 px to columns 34-49
    assert torch.all(visible[0, :, 34:50] == 2.0) and torch.all(visible[0, :, 52:60] == 10.0)
    assert torch.all(visible[4, :, 14:30] == 2.0) and torch.all(visible[4, :, 4:12] == 10.0)


def test_the_occluding_warp_smears_a_near_surface_over_the_background_as_a_camera_does():
    """Against the five views composited with the square in front, the occluding warp reproduces the bands where the
    square smears over the wall (the backward warp erodes the square there instead) and halves the error overall;
    what it cannot know is only the wall the square hid."""
    image, K_view, translations, depth, truth = near_square_over_background()
    occluding = apply_camera_shake_occluding(image, K_view, torch.zeros(5, 3), translations, depth, False)[0, 0, 12]
    grid = shake_sample_grid(K_view, torch.zeros(5, 3), translations, depth)
    backward = apply_camera_shake_with_depth(image, grid, linear_light=False)[0, 0, 12]
    outward = torch.cat([torch.arange(14, 24), torch.arange(40, 50)])  # wall pixels the moving square covers
    assert torch.allclose(occluding[outward], truth[outward], atol=1e-4)
    assert (backward[outward] - truth[outward]).abs().max() > 0.1
    inner = slice(4, -4)
    assert (occluding - truth)[inner].abs().mean() < 0.6 * (backward - truth)[inner].abs().mean()


def test_the_occluding_warp_is_the_rotation_warp_without_translation_and_passes_gradients():
    """Without translation every depth moves alike, so the occluding warp equals the homography warp; with it, the
    path's translations and the image get finite gradients."""
    image = textured(4)
    depth = 0.5 + torch.rand(48, 64, generator=torch.Generator().manual_seed(2)) * 4.0
    rotvecs = torch.tensor([[0.01, -0.02, 0.03], [0.0, 0.0, 0.0], [-0.02, 0.01, -0.01]])
    occluding = apply_camera_shake_occluding(image, K, rotvecs, torch.zeros(3, 3), depth)
    assert torch.allclose(occluding, apply_camera_shake(image, rotation_homographies(K, rotvecs)), atol=1e-4)
    model = CameraShake(1, num_samples=5, seed=1, translation=True, parallax=True, occlusion=True)
    with torch.no_grad():
        model.translation_coefficients.fill_(1.0)
    image.requires_grad_(True)
    out = model(image, K, torch.tensor([0]), centred=True, depth=depth)
    ((out - textured(5)) ** 2).mean().backward()
    assert model.translation_coefficients.grad is not None and image.grad is not None
    assert (
        torch.isfinite(model.translation_coefficients.grad).all()
        and model.translation_coefficients.grad.abs().sum() > 0
    )
    assert torch.isfinite(image.grad).all()
