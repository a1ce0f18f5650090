"""splat_bilinear: the shared point-to-grid splat of the simulator's motion kernels and the shake paths' kernel."""

import pytest
import torch

from gsmsdr_ns.ops.splat import splat_bilinear


def test_a_point_on_a_cell_lands_whole_and_between_cells_splits_bilinearly() -> None:
    grid = splat_bilinear(torch.tensor([[2.0, 1.0]]), torch.tensor([3.0]), 5).reshape(5, 5)
    expected = torch.zeros(5, 5)
    expected[1, 2] = 3.0
    assert torch.equal(grid, expected)
    grid = splat_bilinear(torch.tensor([[1.25, 2.5]]), torch.ones(1), 5).reshape(5, 5)
    assert grid[2, 1] == pytest.approx(0.375) and grid[2, 2] == pytest.approx(0.125)
    assert grid[3, 1] == pytest.approx(0.375) and grid[3, 2] == pytest.approx(0.125)
    assert grid.sum() == pytest.approx(1.0)


def test_points_beyond_the_grid_land_on_its_border_and_keep_their_weight() -> None:
    points = torch.tensor([[-4.0, 2.0], [9.0, 9.0], [4.0, 4.0]], dtype=torch.float64)
    grid = splat_bilinear(points, torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64), 5).reshape(5, 5)
    assert grid.dtype == torch.float64
    assert grid[2, 0] == 1.0 and grid[4, 4] == 2.5 and grid.sum() == 3.5
    assert torch.equal(splat_bilinear(torch.tensor([[0.7, -3.0]]), torch.ones(1), 1), torch.ones(1))


def test_bad_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="points"):
        splat_bilinear(torch.zeros(3, 3), torch.ones(3), 5)
    with pytest.raises(ValueError, match="size"):
        splat_bilinear(torch.zeros(3, 2), torch.ones(3), 0)
